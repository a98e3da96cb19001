"""RepNet pose-lifting service: 2D keypoints in, 3D pose and camera out, over HTTP and gRPC."""
