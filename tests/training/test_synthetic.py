"""Synthetic warm start: random cameras look at an upright person the way Human3.6M's do."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from repnet.core import geometry, skeleton
from repnet.train import data, metrics, synthetic
from tests.training.conftest import STANDING

HEAD, LEFT_ANKLE, RIGHT_ANKLE = 10, 6, 3


def _world_standing() -> np.ndarray:
    # Template (x right, y down, z away) -> world (Z up): the person stands facing world -Y.
    return (STANDING[:, [0, 2, 1]] * [1, 1, -1]).astype(np.float32)


def test_random_views_are_rotations_and_keep_the_person_in_front_of_the_camera() -> None:
    rot, position = synthetic.random_views(2000, torch.Generator().manual_seed(0))
    eye = torch.eye(3, dtype=rot.dtype).expand_as(rot)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), eye)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(2000, dtype=rot.dtype))
    assert position[:, 2].min() >= synthetic.DISTANCE_M[0] and position[:, 2].max() <= synthetic.DISTANCE_M[1]


def test_projected_people_stand_upright_inside_the_image_at_a_plausible_size() -> None:
    gen = torch.Generator().manual_seed(1)
    world = torch.from_numpy(np.repeat(_world_standing()[None], 500, axis=0))
    rot, position = synthetic.random_views(500, gen)
    pixels = synthetic.project(world, rot, position).numpy()
    feet = pixels[:, [LEFT_ANKLE, RIGHT_ANKLE], 1].mean(axis=1)
    assert np.all(pixels[:, HEAD, 1] < feet)  # image y points down: the head is above the feet
    height = feet - pixels[:, HEAD, 1]
    # Human3.6M: up to ~420 px tall, median 327; this 1.57 m person at 3.5-6.5 m: 280-520 px
    assert 200 < height.min() and height.max() < 600
    assert np.all((pixels > -200) & (pixels < 1200))


def test_a_level_camera_in_front_sees_the_right_side_on_the_image_left() -> None:
    # Azimuth 0, elevation 0: the camera looks along world +Y at a person facing -Y, i.e. at
    # the camera, so the person's right hip appears on the image's left, as in the template.
    level = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]], dtype=torch.float64)
    pixels = synthetic.project(
        torch.from_numpy(_world_standing()[None]), level, torch.tensor([[0.0, 0.0, 5.0]], dtype=torch.float64)
    )[0]
    assert pixels[skeleton.RIGHT_HIP, 0] < pixels[skeleton.LEFT_HIP, 0]
    template = data.align_to_template(_world_standing()[None].astype(np.float64))[0]
    assert template[skeleton.RIGHT_HIP, 0] < 0 < template[skeleton.LEFT_HIP, 0]


def test_sample_pairs_each_view_with_the_aligned_pose_of_the_same_frame() -> None:
    rng = np.random.default_rng(0)
    world = np.stack([_world_standing() + rng.normal(0, 30, (17, 3)).astype(np.float32) for _ in range(50)])
    world -= world[:, :1]
    aligned = torch.from_numpy(data.align_to_template(world) / 1000)
    gen = torch.Generator().manual_seed(3)
    pixels, target, no_rotation = synthetic.sample(torch.from_numpy(world), aligned, 64, 0.0, gen)
    assert no_rotation is None
    assert pixels.shape == (64, 17, 2) and target.shape == (64, 17, 3)
    # Every target is one of the aligned poses, and noise-free pixels are those of its world pose.
    gen = torch.Generator().manual_seed(3)
    idx = torch.randint(0, 50, (64,), generator=gen)
    torch.testing.assert_close(target, aligned[idx])
    noisy, _, _ = synthetic.sample(
        torch.from_numpy(world), aligned, 64, 8.0, torch.Generator().manual_seed(3)
    )
    spread = (noisy - pixels).abs()
    assert 0 < spread.mean() < 8


def _jittered_poses(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """20 jittered standing world poses (mm, pelvis at the origin), the same aligned to the
    template, and the rotations that aligned them."""
    rng = np.random.default_rng(seed)
    world = np.stack([_world_standing() + rng.normal(0, 30, (17, 3)).astype(np.float32) for _ in range(20)])
    world -= world[:, :1]
    aligned = data.align_to_template(world).astype(np.float64)
    _, align_rotations, _ = data.procrustes(world.astype(np.float64), aligned)
    return world, aligned, align_rotations


def _residual_px(
    pixels: torch.Tensor, target: torch.Tensor, to_camera: torch.Tensor, position: torch.Tensor
) -> torch.Tensor:
    """(B,) mean distance (px) of the pixels from the (B, J, 3) targets seen through the camera
    targets at the synthetic positions, both centred, the targets' projection best scaled."""
    in_camera = target.to(torch.float64) @ to_camera.to(torch.float64).transpose(1, 2) + position[:, None]
    seen = synthetic.FOCAL_PX * in_camera[..., :2] / in_camera[..., 2:3]
    seen = seen - seen.mean(dim=1, keepdim=True)
    shown = (pixels - pixels.mean(dim=1, keepdim=True)).to(torch.float64)
    ratio = (seen * shown).sum(dim=(1, 2)) / (seen**2).sum(dim=(1, 2))
    return (seen * ratio[:, None, None] - shown).norm(dim=-1).mean(dim=1)


def test_the_camera_target_rotates_the_template_pose_into_the_synthetic_camera() -> None:
    world, aligned, align_rotations = _jittered_poses(1)
    _, target, to_camera = synthetic.sample(
        torch.from_numpy(world),
        torch.from_numpy(aligned / 1000),
        32,
        0.0,
        torch.Generator().manual_seed(5),
        torch.from_numpy(align_rotations),
    )
    assert to_camera is not None
    gen = torch.Generator().manual_seed(5)
    idx = torch.randint(0, 20, (32,), generator=gen)
    view, _ = synthetic.random_views(32, gen)
    in_camera = torch.from_numpy(world)[idx].to(torch.float64) @ view.transpose(1, 2)  # (32, 17, 3) mm
    from_template = target.to(torch.float64) @ to_camera.to(torch.float64).transpose(1, 2)  # metres, scaled
    ratio = (in_camera * from_template).sum(dim=(1, 2)) / (from_template**2).sum(dim=(1, 2))
    torch.testing.assert_close(from_template * ratio[:, None, None], in_camera, atol=0.5, rtol=0.0)


def test_the_ray_target_is_the_camera_target_seen_along_the_ray_to_the_pelvis() -> None:
    world, aligned, align_rotations = _jittered_poses(2)
    args = (torch.from_numpy(world), torch.from_numpy(aligned / 1000), 32, 0.0)
    rotations = torch.from_numpy(align_rotations)
    _, _, axis = synthetic.sample(*args, torch.Generator().manual_seed(5), rotations, "axis")
    _, _, ray = synthetic.sample(*args, torch.Generator().manual_seed(5), rotations, "ray")
    assert axis is not None and ray is not None
    gen = torch.Generator().manual_seed(5)
    torch.randint(0, 20, (32,), generator=gen)
    _, position = synthetic.random_views(32, gen)
    turn = torch.from_numpy(geometry.rotation_to_ray(position.numpy())).to(torch.float32)
    torch.testing.assert_close(turn @ ray, axis, atol=1e-5, rtol=0.0)
    # The people stand off the axis, so the two targets differ; by at most the largest offset angle.
    angle = torch.rad2deg(torch.arccos(((turn.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))
    assert 0 < angle.min() and angle.max() < 20.0
    with pytest.raises(ValueError, match="axis or ray"):
        synthetic.sample(*args, torch.Generator().manual_seed(5), rotations, "sideways")


def test_the_mirror_of_an_aligned_pose_is_the_alignment_of_the_mirrored_world_pose() -> None:
    world, aligned, _ = _jittered_poses(3)
    mirrored_world = synthetic.mirror(torch.from_numpy(world)).numpy()
    np.testing.assert_allclose(
        data.align_to_template(mirrored_world), synthetic.mirror(torch.from_numpy(aligned)).numpy(), atol=1e-2
    )
    # A mirror image keeps every bone's length but is not the pose itself.
    np.testing.assert_allclose(
        metrics.symmetry_error(world), metrics.symmetry_error(mirrored_world), atol=1e-3
    )
    assert np.abs(mirrored_world - world).max() > 50


def test_mirrored_samples_keep_pixels_target_and_camera_target_consistent() -> None:
    world, aligned, align_rotations = _jittered_poses(4)
    args = (torch.from_numpy(world), torch.from_numpy(aligned / 1000), 64, 0.0)
    rotations = torch.from_numpy(align_rotations)
    plain = synthetic.sample(*args, torch.Generator().manual_seed(6), rotations)
    gen = torch.Generator().manual_seed(6)
    pixels, target, to_camera = synthetic.sample(*args, gen, rotations, mirror_prob=0.5)
    assert to_camera is not None and plain[2] is not None
    gen = torch.Generator().manual_seed(6)
    torch.randint(0, 20, (64,), generator=gen)
    _, position = synthetic.random_views(64, gen)
    flip = torch.rand(64, generator=gen) < 0.5
    assert 10 < int(flip.sum()) < 54
    # Unmirrored poses are drawn exactly as without mirroring; mirrored ones are mirror images.
    torch.testing.assert_close(target[~flip], plain[1][~flip])
    torch.testing.assert_close(pixels[~flip], plain[0][~flip])
    torch.testing.assert_close(target[flip], synthetic.mirror(plain[1][flip]))
    # Every pose's pixels are its target seen through its camera target (up to scale and shift).
    residual = _residual_px(pixels, target, to_camera, position)
    assert residual.max() < 2.0, residual.max()


@pytest.mark.parametrize("power", [1.0, 2.0, 3.0])
def test_the_noise_power_keeps_the_largest_sigma_and_makes_most_poses_cleaner(power: float) -> None:
    """sigma = noise_px * u ** power: the pixel noise's mean square is noise_px^2 / (2 power + 1)."""
    world = torch.from_numpy(np.repeat(_world_standing()[None], 4, axis=0))
    aligned = torch.from_numpy(data.align_to_template(world.numpy()) / 1000)

    def pixels(noise_px: float) -> torch.Tensor:
        return synthetic.sample(
            world, aligned, 20000, noise_px, torch.Generator().manual_seed(5), noise_power=power
        )[0]

    noise = (pixels(20.0) - pixels(0.0)).double()
    assert noise.pow(2).mean().item() == pytest.approx(400.0 / (2 * power + 1), rel=0.03)
    per_pose = noise.std(dim=(1, 2))  # about each pose's sigma: the median pose has 20 * 0.5 ** power
    assert per_pose.median().item() == pytest.approx(20.0 * 0.5**power, rel=0.1)


def test_turned_limbs_keep_every_bone_and_the_torso_and_turn_about_their_joints() -> None:
    world, _, _ = _jittered_poses(7)
    poses = torch.from_numpy(world)
    turns = synthetic.random_turns((20, len(synthetic.LIMB_SEGMENTS)), 20.0, torch.Generator().manual_seed(1))
    torch.testing.assert_close(
        turns @ turns.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(turns)
    )
    turned = synthetic.turn_limbs(poses, turns)
    bones = np.array(skeleton.BONES)
    torch.testing.assert_close(
        (turned[:, bones[:, 1]] - turned[:, bones[:, 0]]).norm(dim=-1),
        (poses[:, bones[:, 1]] - poses[:, bones[:, 0]]).norm(dim=-1),
        atol=1e-3,
        rtol=0.0,
    )
    unmoved = [
        j for j in range(skeleton.NUM_JOINTS) if j not in {m for _, ms in synthetic.LIMB_SEGMENTS for m in ms}
    ]
    assert set(skeleton.TORSO_JOINTS) <= set(unmoved)
    torch.testing.assert_close(turned[:, unmoved], poses[:, unmoved])
    assert (turned - poses).norm(dim=-1).max() > 50.0
    # Known value: the right forearm alone turned 90 degrees about an axis across it moves the
    # wrist by sqrt(2) forearm lengths, and the elbow stays.
    elbow, wrist = skeleton.JOINT_NAMES.index("right_elbow"), skeleton.JOINT_NAMES.index("right_wrist")
    k = next(i for i, (pivot, _) in enumerate(synthetic.LIMB_SEGMENTS) if pivot == elbow)
    forearm = (poses[0, wrist] - poses[0, elbow]).to(torch.float64)
    axis = torch.linalg.cross(forearm, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    axis = axis / axis.norm()
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    one = torch.eye(3, dtype=torch.float64).repeat(1, len(synthetic.LIMB_SEGMENTS), 1, 1)
    one[0, k] = torch.eye(3, dtype=torch.float64) + cross + cross @ cross  # Rodrigues at 90 degrees
    moved = synthetic.turn_limbs(poses[:1], one)
    assert float((moved[0, wrist] - poses[0, wrist]).norm()) == pytest.approx(
        float(np.sqrt(2.0) * forearm.norm()), rel=1e-4
    )
    torch.testing.assert_close(moved[0, :wrist], poses[0, :wrist])


def test_samples_with_turned_limbs_turn_the_world_pose_and_its_target_alike() -> None:
    world, aligned, align_rotations = _jittered_poses(8)
    args = (torch.from_numpy(world), torch.from_numpy(aligned / 1000), 64, 0.0)
    rotations = torch.from_numpy(align_rotations)
    plain = synthetic.sample(*args, torch.Generator().manual_seed(9), rotations)
    pixels, target, to_camera = synthetic.sample(
        *args, torch.Generator().manual_seed(9), rotations, limb_turn_deg=20.0, limb_turn_prob=0.5
    )
    assert to_camera is not None and plain[2] is not None
    changed = (target - plain[1]).norm(dim=-1).amax(dim=1) > 1e-3  # metres
    assert 10 < int(changed.sum()) < 54  # about half of the poses turned
    torch.testing.assert_close(to_camera, plain[2])  # the same views and alignment
    torch.testing.assert_close(target[~changed], plain[1][~changed])
    # The turned targets keep their bones, and their pixels are still the target seen through the
    # camera target: the world pose turned exactly as its aligned copy.
    bones = np.array(skeleton.BONES)
    torch.testing.assert_close(
        (target[:, bones[:, 1]] - target[:, bones[:, 0]]).norm(dim=-1),
        (plain[1][:, bones[:, 1]] - plain[1][:, bones[:, 0]]).norm(dim=-1),
        atol=1e-5,
        rtol=0.0,
    )
    gen = torch.Generator().manual_seed(9)
    torch.randint(0, 20, (64,), generator=gen)
    _, position = synthetic.random_views(64, gen)
    residual = _residual_px(pixels, target, to_camera, position)
    assert residual.max() < 2.0, residual.max()
    # Without the turn applied to the world pose, the pixels would not match the turned target.
    assert _residual_px(plain[0], target, to_camera, position)[changed].min() > 2.0
    with pytest.raises(ValueError, match="align_rotations"):
        synthetic.sample(*args, torch.Generator().manual_seed(9), limb_turn_deg=20.0)
