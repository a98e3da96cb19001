"""Does Blender read a `repnet lift -o clip.bvh` file as repnet.io.bvh means it? Run with a Python that
has Blender's `bpy` module (pip install bpy, in its own environment: not a dependency of repnet):

    /path/to/bpy-env/bin/python bench/blender_bvh.py clip.bvh

Blender's own BVH importer (bpy.ops.import_anim.bvh, Y up, -Z forward) builds the armature and its
action; every frame's bone heads, in Blender's Z-up world, are compared with repnet.io.bvh's forward
kinematics of the parsed file. Prints the bone count, frame rate and the largest difference (mm).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import bpy  # noqa: E402  (Blender as a module; only here)

from repnet.io import bvh  # noqa: E402


def main(path: Path) -> dict[str, object]:
    """Import `path` into an empty Blender scene and compare its bone heads with our FK."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_anim.bvh(
        filepath=str(path), axis_forward="-Z", axis_up="Y", rotate_mode="NATIVE", update_scene_fps=True
    )
    armature = next(o for o in bpy.data.objects if o.type == "ARMATURE")
    scene = bpy.context.scene
    motion = bvh.parse_bvh(path.read_text())
    ours = bvh.forward_kinematics(motion) @ np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # Y up -> Z up
    worst = 0.0
    for t in range(len(ours)):
        scene.frame_set(scene.frame_start + t)
        for j, name in enumerate(motion.names):
            head = np.array(armature.matrix_world @ armature.pose.bones[name].head)
            worst = max(worst, float(np.linalg.norm(head - ours[t, j])))
    return {
        "file": str(path),
        "blender": bpy.app.version_string,
        "bones": len(armature.data.bones),
        "frames": len(ours),
        "scene_fps": scene.render.fps / scene.render.fps_base,
        "max_head_difference_mm": worst * 1000,
    }


if __name__ == "__main__":
    print(json.dumps(main(Path(sys.argv[1])), indent=2))
