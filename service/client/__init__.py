"""Clients of a running service: LiftClient (HTTP), StreamClient (gRPC LiftStream), their result."""
