"""The core (numpy only, imported by every other part): joints and keypoint formats, the input rules,
camera geometry, the reply's fields, the temporal contract and the errors."""
