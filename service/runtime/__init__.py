"""Models in this process (onnxruntime): the single-frame and temporal lifters, their batchers, the
model catalog, tracks and temporal plans, and the replies built from the models' answers."""
