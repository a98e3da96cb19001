"""repnet.train.density and repnet.train.plausibility: the pose density behind the plausibility output, how
it travels in the ONNX file with the critic, and how adapt rebuilds a parent's plausibility."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch
from sklearn.mixture import GaussianMixture  # type: ignore[import-untyped]

from repnet.core import skeleton
from repnet.train import checkpoint, density, export, metadata
from repnet.train import plausibility as plausibility_of
from repnet.train.config import RepNetConfig
from repnet.train.model import Critic, LiftingGraph, Plausibility, RepNet
from repnet.train.plausibility import Score
from tests.training.conftest import STANDING

TINY = RepNetConfig(width=32, critic_width=16, kcs_width=8)


@pytest.fixture(scope="module")
def real() -> np.ndarray:
    """600 poses around the standing one (mm), limbs of one person: the same bones every time."""
    rng = np.random.default_rng(0)
    poses = np.repeat(STANDING[None].astype(np.float64), 600, axis=0)
    for parent, child in skeleton.BONES:  # turn each bone a little, keep its length
        bone = STANDING[child] - STANDING[parent]
        turned = bone + rng.normal(0, 0.15 * np.linalg.norm(bone), (600, 3))
        turned *= np.linalg.norm(bone) / np.linalg.norm(turned, axis=1, keepdims=True)
        poses[:, child] = poses[:, parent] + turned
    return poses.astype(np.float32)


@pytest.fixture(scope="module")
def fitted(real: np.ndarray) -> density.PoseDensity:
    return density.PoseDensity.fit(real, components=3, dims=6)


def test_the_density_is_the_mixture_of_the_directions_plus_the_gaussian_of_the_proportions(
    real: np.ndarray, fitted: density.PoseDensity
) -> None:
    """Against scikit-learn's mixture on the same PCA codes and the Gaussian's log density by hand."""
    parents, children = zip(*skeleton.BONES, strict=True)
    bones = real[:, list(children)].astype(np.float64) - real[:, list(parents)]
    lengths = np.linalg.norm(bones, axis=-1)
    directions = (bones / lengths[..., None]).reshape(len(real), -1)
    proportions = np.log(lengths) - np.log(lengths).mean(axis=1, keepdims=True)
    centred = directions - directions.mean(axis=0)
    codes = centred @ np.linalg.svd(centred, full_matrices=False)[2][:6].T
    mixture = GaussianMixture(3, covariance_type="full", random_state=0, reg_covar=1e-4, max_iter=200)
    expected = mixture.fit(codes).score_samples(codes)
    cov = (np.cov(proportions.T) + density.LENGTH_FLOOR**2 * np.eye(16)) * density.LENGTH_WIDEN**2
    off = proportions - proportions.mean(axis=0)
    expected += -0.5 * np.einsum("ni,ij,nj->n", off, np.linalg.inv(cov), off)
    expected += -0.5 * (np.linalg.slogdet(cov)[1] + 16 * math.log(2 * math.pi))
    with torch.no_grad():
        got = fitted(torch.from_numpy(real / 1000.0)).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=2e-2)


def test_size_and_place_do_not_matter_but_a_longer_limb_or_one_side_longer_does(
    real: np.ndarray, fitted: density.PoseDensity
) -> None:
    pose = torch.from_numpy(real[:1] / 1000.0)
    longer = pose.clone()
    longer[0, 13] += 0.3 * (pose[0, 13] - pose[0, 12])  # the left forearm 30 % longer
    with torch.no_grad():
        base = fitted(pose)
        assert torch.allclose(fitted(pose * 1.4 + 0.2), base, atol=1e-3)  # taller, elsewhere
        assert fitted(longer) < base - 5.0


def _exported(tmp_path: Path, score: torch.nn.Module, with_critic: Critic | None, kind: Score) -> Path:
    """A tiny model whose plausibility is `score` calibrated on its own generator's answers to other
    inputs (so that its answers spread over [0, 1])."""
    torch.manual_seed(0)
    generator = RepNet(TINY).eval()
    points = torch.from_numpy(np.random.default_rng(1).normal(0, 100, (300, 17, 2)).astype(np.float32) + 500)
    with torch.no_grad():
        answers = LiftingGraph(generator)(points, torch.ones(300, 17))[0].numpy()
    plausibility, table, bones = plausibility_of.build(score, answers)
    meta = metadata.build_metadata(TINY, "tiny", plausibility=plausibility_of.metadata(kind, table, bones))
    path = tmp_path / f"{kind}.onnx"
    export.export_onnx(generator, path, meta, plausibility, critic=with_critic)
    return path


def _run(path: Path) -> list[np.ndarray]:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    points = (np.random.default_rng(2).normal(0, 100, (16, 17, 2)) + 500).astype(np.float32)
    return list(session.run(None, {"keypoints_2d": points, "visibility": np.ones((16, 17), np.float32)}))


def test_the_density_and_the_critic_travel_in_the_onnx_file_and_adapt_rebuilds_the_plausibility(
    tmp_path: Path, fitted: density.PoseDensity
) -> None:
    critic = Critic(TINY).eval()
    path = _exported(tmp_path, fitted, critic, "density")
    names = [o.name for o in ort.InferenceSession(str(path)).get_outputs()]
    assert names == ["pose_3d", "camera", "plausibility", "critic"]
    pose, _, plausible, critic_score = _run(path)
    with torch.no_grad():
        np.testing.assert_allclose(critic_score, critic(torch.from_numpy(pose) / 1000).numpy(), atol=1e-5)
    state = checkpoint.load(path)
    for name, value in fitted.state_dict().items():
        assert torch.equal(state["density"][name], value), name
    for name, value in critic.state_dict().items():
        assert torch.equal(state["critic"][name], value), name
    meta = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    rebuilt = plausibility_of.from_state(state, meta)
    assert isinstance(rebuilt.score, density.PoseDensity)
    with torch.no_grad():
        np.testing.assert_allclose(rebuilt(torch.from_numpy(pose) / 1000).numpy(), plausible, atol=1e-6)
    assert 0.0 < plausible.mean() < 1.0 and np.unique(plausible).size > 4
    assert "density" in meta["plausibility"]


def test_a_model_exported_before_the_density_gives_back_its_critic_and_its_plausibility(
    tmp_path: Path,
) -> None:
    """v6's layout: the critic is the plausibility's score, its weights under plausibility.critic.,
    its table under critic_scores_at_quantiles."""
    critic = Critic(TINY).eval()
    path = _exported(tmp_path, critic, None, "critic")
    model = onnx.load(str(path))
    for init in model.graph.initializer:
        init.name = init.name.replace(checkpoint.SCORE_PREFIX, checkpoint.LEGACY_CRITIC_PREFIX)
    for node in model.graph.node:
        node.input[:] = [
            n.replace(checkpoint.SCORE_PREFIX, checkpoint.LEGACY_CRITIC_PREFIX) for n in node.input
        ]
    meta = {p.key: p.value for p in model.metadata_props}
    calibration = json.loads(meta["plausibility_calibration"])
    calibration["critic_scores_at_quantiles"] = calibration.pop("scores_at_quantiles")
    del calibration["score"]
    meta["plausibility_calibration"] = json.dumps(calibration)
    del model.metadata_props[:]
    for key, value in meta.items():
        model.metadata_props.add(key=key, value=value)
    legacy = tmp_path / "legacy.onnx"
    onnx.save(model, str(legacy))
    pose, _, plausible = _run(legacy)
    state = checkpoint.load(legacy)
    assert state["density"] == {} and state["critic"].keys() == critic.state_dict().keys()
    for name, value in critic.state_dict().items():
        assert torch.equal(state["critic"][name], value), name
    rebuilt = plausibility_of.from_state(state, meta)
    assert isinstance(rebuilt.score, Critic)
    with torch.no_grad():
        np.testing.assert_allclose(rebuilt(torch.from_numpy(pose) / 1000).numpy(), plausible, atol=1e-6)
    assert np.unique(plausible).size > 4


def test_a_plausibility_is_zero_outside_the_bone_range_and_a_percentile_inside(
    fitted: density.PoseDensity,
) -> None:
    real = STANDING[None] + np.random.default_rng(3).normal(0, 10, (200, 17, 3))
    plausibility, table, _ = plausibility_of.build(fitted, real.astype(np.float32))
    assert isinstance(plausibility, Plausibility) and np.all(np.diff(table) >= 0)
    poses = torch.from_numpy(real[:4].astype(np.float32) / 1000)
    giant = poses.clone()
    giant[:, 13] = giant[:, 12] + (giant[:, 13] - giant[:, 12]) * 4
    with torch.no_grad():
        inside, outside = plausibility(poses).numpy(), plausibility(giant).numpy()
    assert np.all((inside > 0) & (inside <= 1)) and np.all(outside == 0)
