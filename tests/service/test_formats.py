"""Tests for the detector keypoint formats and their mapping onto the model's joints."""

from __future__ import annotations

import numpy as np
import pytest

from repnet.core.format_hints import format_table
from repnet.core.formats import (
    FORMATS,
    MODEL_JOINTS,
    MODEL_PARENTS,
    KeypointFormat,
    from_model_joints,
    to_model_joints,
)
from repnet.runtime.lifter import Lifter

# A standing person in pixels (image y down), Human3.6M 17-joint order; the spine sits off the
# pelvis-thorax midpoint and the thorax above the shoulders, as in the real skeleton.
STANDING = np.array(
    [
        [500, 500], [470, 502], [468, 620], [466, 735], [530, 498], [532, 618], [534, 733],
        [502, 430], [500, 360], [501, 330], [500, 290], [540, 372], [560, 440], [570, 505],
        [460, 370], [441, 438], [430, 503],
    ],
    dtype=np.float32,
)  # fmt: skip

COCO_ORDER = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip


@pytest.fixture
def poses() -> np.ndarray:
    rng = np.random.default_rng(0)
    return (STANDING[None] + rng.normal(0, 15, size=(8, 17, 2))).astype(np.float32)  # (8, 17, 2)


def test_formats_are_registered_with_their_joint_counts() -> None:
    counts = {name: len(fmt.joint_names) for name, fmt in FORMATS.items()}
    assert counts == {
        "h36m17": 17, "mpii16": 16, "coco17": 17, "body25": 25, "mediapipe33": 33,
        "coco18": 18, "body25b": 25, "halpe26": 26, "wholebody133": 133,
    }  # fmt: skip
    for fmt in FORMATS.values():
        assert len(set(fmt.joint_names)) == len(fmt.joint_names)
        assert len(fmt.sources) == len(MODEL_JOINTS)


def test_published_joint_orders() -> None:
    assert FORMATS["coco17"].joint_names == COCO_ORDER
    body25 = FORMATS["body25"].joint_names
    assert (body25[1], body25[8], body25[19], body25[24]) == ("neck", "mid_hip", "left_big_toe", "right_heel")
    mp = FORMATS["mediapipe33"].joint_names
    assert (mp[0], mp[11], mp[16], mp[23], mp[28], mp[32]) == (
        "nose", "left_shoulder", "right_wrist", "left_hip", "right_ankle", "right_foot_index",
    )  # fmt: skip


def test_published_joint_orders_of_the_openpose_halpe_and_wholebody_formats() -> None:
    assert FORMATS["coco18"].joint_names == (
        "nose", "neck", "right_shoulder", "right_elbow", "right_wrist", "left_shoulder", "left_elbow",
        "left_wrist", "right_hip", "right_knee", "right_ankle", "left_hip", "left_knee", "left_ankle",
        "right_eye", "left_eye", "right_ear", "left_ear",
    )  # fmt: skip
    feet = ("left_big_toe", "left_small_toe", "left_heel", "right_big_toe", "right_small_toe", "right_heel")
    assert FORMATS["body25b"].joint_names == (*COCO_ORDER, "upper_neck", "head_top", *feet)
    assert FORMATS["halpe26"].joint_names == (
        *COCO_ORDER, "head", "neck", "hip", "left_big_toe", "right_big_toe", "left_small_toe",
        "right_small_toe", "left_heel", "right_heel",
    )  # fmt: skip
    wholebody = FORMATS["wholebody133"].joint_names
    assert wholebody[:23] == (*COCO_ORDER, *feet)
    assert (wholebody[23], wholebody[90], wholebody[91], wholebody[111], wholebody[112], wholebody[132]) == (
        "face_0", "face_67", "left_hand_0", "left_hand_20", "right_hand_0", "right_hand_20",
    )  # fmt: skip


# Per new format, the source joint(s) each model joint reads (None: imputed by the model).
NEW_TABLES = {
    "coco18": {"pelvis": ("left_hip", "right_hip"), "thorax": ("neck",), "neck": ("nose",), "head": None},
    "body25b": {"pelvis": ("left_hip", "right_hip"), "thorax": ("left_shoulder", "right_shoulder"),
                "neck": ("upper_neck",), "head": ("head_top",)},
    "halpe26": {"pelvis": ("hip",), "thorax": ("neck",), "neck": ("nose",), "head": ("head",)},
    "wholebody133": {"pelvis": ("left_hip", "right_hip"), "thorax": ("left_shoulder", "right_shoulder"),
                     "neck": ("nose",), "head": None},
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(NEW_TABLES))
def test_new_tables_map_each_source_joint_onto_its_model_joint(name: str) -> None:
    """A pose whose every source joint holds its own index (x = k, y = 1000 + k) lands on the model
    joints the table names: limbs by name, the torso and head as NEW_TABLES says, spine imputed."""
    fmt = FORMATS[name]
    k = np.arange(len(fmt.joint_names), dtype=np.float32)
    points = np.stack([k, 1000 + k], axis=-1)[None]  # (1, K, 2)
    out, visible, derived, imputed = to_model_joints(fmt, points, np.ones((1, len(k)), bool))
    for j, joint in enumerate(MODEL_JOINTS):
        sources = NEW_TABLES[name].get(joint, () if joint == "spine" else (joint,))
        if not sources:
            assert imputed[0, j] and not visible[0, j], joint
            continue
        want = np.mean([fmt.joint_names.index(s) for s in sources])
        np.testing.assert_allclose(out[0, j], [want, 1000 + want], err_msg=f"{name} {joint}")
        assert visible[0, j] and derived[0, j] == (len(sources) == 2), joint


def test_wholebody_reads_only_the_body_as_coco17(poses: np.ndarray) -> None:
    coco, coco_visible = from_model_joints(FORMATS["coco17"], poses)
    rng = np.random.default_rng(1)
    rest = rng.uniform(0, 1000, size=(8, 133 - 17, 2)).astype(np.float32)  # feet, face, hands: anything
    wholebody = np.concatenate([np.nan_to_num(coco), rest], axis=1)
    visible = np.concatenate([coco_visible, np.ones((8, 133 - 17), bool)], axis=1)
    got = to_model_joints(FORMATS["wholebody133"], wholebody, visible)
    want = to_model_joints(FORMATS["coco17"], np.nan_to_num(coco), coco_visible)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)


def test_mpii_table_matches_the_stacked_hourglass_mapping() -> None:
    expected = (6, 2, 1, 0, 3, 4, 5, None, 7, 8, 9, 13, 14, 15, 12, 11, 10)
    got = tuple(src[0] if src else None for src in FORMATS["mpii16"].sources)
    assert got == expected
    assert all(len(src) <= 1 for src in FORMATS["mpii16"].sources)


def test_h36m_table_is_the_identity(poses: np.ndarray) -> None:
    fmt = FORMATS["h36m17"]
    points, visible, derived, imputed = to_model_joints(fmt, poses, np.ones(poses.shape[:2], bool))
    np.testing.assert_array_equal(points, poses)
    assert visible.all() and not derived.any() and not imputed.any()


@pytest.mark.parametrize("name", sorted(FORMATS))
def test_round_trip_matches_on_shared_joints(name: str, poses: np.ndarray) -> None:
    fmt = FORMATS[name]
    src_points, src_visible = from_model_joints(fmt, poses)
    assert src_points.shape == (8, len(fmt.joint_names), 2)
    points, visible, derived, imputed = to_model_joints(fmt, src_points, src_visible)
    for j, src in enumerate(fmt.sources):
        if len(src) == 1:  # shared joint: exact
            np.testing.assert_allclose(points[:, j], poses[:, j], atol=1e-4)
        elif len(src) == 2:  # derived joint: the midpoint of the ground-truth joints it maps from
            parts = [next(k for k, s in enumerate(fmt.sources) if s == (i,)) for i in src]
            np.testing.assert_allclose(points[:, j], poses[:, parts].mean(axis=1), atol=1e-3)
        assert visible[:, j].all() == bool(src) and imputed[:, j].all() == (not src)
        assert derived[:, j].all() == (len(src) == 2)


def test_coco_flags_derived_and_imputed_joints(poses: np.ndarray) -> None:
    src_points, src_visible = from_model_joints(FORMATS["coco17"], poses)
    _, visible, derived, imputed = to_model_joints(FORMATS["coco17"], src_points, src_visible)
    names = np.array(MODEL_JOINTS)
    assert set(names[derived[0]]) == {"pelvis", "thorax"}
    assert set(names[imputed[0]]) == {"spine", "head"}
    np.testing.assert_array_equal(visible, ~imputed)


def test_derived_joint_is_visible_only_if_all_sources_are(poses: np.ndarray) -> None:
    fmt = FORMATS["coco17"]
    src_points, src_visible = from_model_joints(fmt, poses)
    left_hip = COCO_ORDER.index("left_hip")
    src_visible[0, left_hip] = False
    src_points[0, left_hip] = np.nan  # a missing joint's coordinates must not leak into the midpoint
    points, visible, derived, imputed = to_model_joints(fmt, src_points, src_visible)
    pelvis, model_left_hip = MODEL_JOINTS.index("pelvis"), MODEL_JOINTS.index("left_hip")
    assert not visible[0, pelvis] and imputed[0, pelvis] and derived[0, pelvis]
    assert not visible[0, model_left_hip] and imputed[0, model_left_hip]
    assert visible[1:, pelvis].all()
    assert np.isfinite(points).all()
    np.testing.assert_array_equal(points[0, ~visible[0]], 0.0)


def test_from_model_joints_leaves_unmapped_joints_not_visible(poses: np.ndarray) -> None:
    fmt = FORMATS["mediapipe33"]
    points, visible = from_model_joints(fmt, poses)
    mapped = {fmt.joint_names[src[0]] for src in fmt.sources if len(src) == 1}
    for k, name in enumerate(fmt.joint_names):
        assert visible[:, k].all() == (name in mapped)
        assert np.isnan(points[:, k]).all() != (name in mapped)
    assert "left_eye" not in mapped and "left_heel" not in mapped


def test_from_model_joints_respects_model_visibility(poses: np.ndarray) -> None:
    fmt = FORMATS["body25"]
    vis17 = np.ones((8, 17), dtype=bool)
    vis17[:, MODEL_JOINTS.index("right_wrist")] = False
    _, visible = from_model_joints(fmt, poses, vis17)
    assert not visible[:, fmt.joint_names.index("right_wrist")].any()
    assert visible[:, fmt.joint_names.index("left_wrist")].all()


def test_wrong_shapes_are_rejected(poses: np.ndarray) -> None:
    with pytest.raises(ValueError, match=r"\(N, 17, 2\)"):
        to_model_joints(FORMATS["coco17"], poses[:, :16], np.ones((8, 16), bool))
    with pytest.raises(ValueError, match="visible"):
        to_model_joints(FORMATS["coco17"], poses, np.ones((8, 16), bool))


def test_table_rejects_bad_sources() -> None:
    with pytest.raises(ValueError, match="bad source"):
        KeypointFormat("bad", ("a", "b"), ((0, 5),) + ((),) * 16)
    with pytest.raises(ValueError, match="expected 17 sources"):
        KeypointFormat("bad", ("a",), ((0,),))


def test_format_table_lists_every_format_and_joint() -> None:
    table = format_table()
    for name in FORMATS:
        assert name in table
    for joint in MODEL_JOINTS:
        assert f"| {joint} |" in table
    assert "mid(left_hip, right_hip)" in table and "— (imputed)" in table


def test_model_joints_and_parents_match_the_bundled_model(lifter: Lifter) -> None:
    assert lifter.info.joint_names == MODEL_JOINTS
    assert lifter.info.parents == MODEL_PARENTS
