"""Files: pose files in (detectors' layouts), JSON, NPZ, CSV and BVH out, plots."""
