"""The gRPC adapter: the PoseLifter servicer (Lift, LiftStream), its wire input and its server."""
