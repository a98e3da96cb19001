"""Benchmarks of the lifting service: the raw-model roof, HTTP and gRPC load, accuracy per format."""
