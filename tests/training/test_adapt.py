"""`repnet adapt`: end to end on a tiny model, lineage, the service loading the result, resume bit for
bit, the refusal of a worse model, and the pieces (holdout split, residuals, the pose prior)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from repnet.cli.main import main as repnet
from repnet.core import skeleton
from repnet.runtime.loading import BUNDLED_CAUSAL, BUNDLED_OFFLINE, load_temporal_lifters
from repnet.server.config import Settings
from repnet.server.startup import load_lifter
from repnet.train import adapt_cli, adapt_report, checkpoint, lineage, metrics, prior, synthetic
from repnet.train.adapt import Adaptation, AdaptConfig, answer, split_holdout, triplets_of
from repnet.train.adapt_report import Figures, worse
from repnet.train.camera import camera_frame, masked_centre, project_weak_perspective
from repnet.train.checkpoint import read_metadata
from repnet.train.config import RepNetConfig
from repnet.train.export import generator_of
from repnet.train.model import MM_PER_UNIT, RepNet, normalize_keypoints
from tests.training.conftest import plant

FAST = ["--threads", "1", "--prior-poses", "2000"]
TEMPORAL_PATHS = {"causal": BUNDLED_CAUSAL, "offline": BUNDLED_OFFLINE}


@pytest.fixture(scope="module")
def parent() -> Path:
    """The bundled model: mirror-averaged, with a calibrated critic."""
    return Settings().model_path


@pytest.fixture(scope="module")
def poses_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """300 prior poses seen by random cameras, a few joints missing: a user's unlabeled 2D."""
    gen = torch.Generator().manual_seed(0)
    world = torch.from_numpy(prior.PosePrior.load().sample(300, np.random.default_rng(2))).double()
    rot, position = synthetic.random_views(len(world), gen)
    pixels = synthetic.project(world, rot, position).numpy()
    rng = np.random.default_rng(3)
    pixels += rng.normal(0, 3.0, pixels.shape)
    pixels[rng.random(pixels.shape[:2]) < 0.05] = np.nan
    path = tmp_path_factory.mktemp("input") / "detections.npz"
    np.savez(path, keypoints=pixels, format="h36m17")
    return path


def adapt(poses: Path, parent: Path, out: Path, *flags: str) -> int:
    return repnet(["adapt", str(poses), "-o", str(out), "--model", str(parent), *FAST, *flags])


def test_adapt_writes_a_model_the_service_serves_with_its_lineage(
    poses_file: Path, parent: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "mine.onnx"
    assert adapt(poses_file, parent, out, "--steps", "4", "--run-dir", str(tmp_path / "run"), "--force") == 0
    printed = capsys.readouterr().out
    assert "reprojection error (px)" in printed and "held-out poses: 30" in printed
    meta = read_metadata(out)
    record = json.loads(meta["lineage"])
    assert record["model_id"] == meta["model_id"] == "mine"
    assert record["parent"] == {
        "model_id": read_metadata(parent)["model_id"],
        "sha256": lineage.file_sha256(parent),
    }
    assert record["inputs"] == [{"input": "detections.npz", "sha256": lineage.file_sha256(poses_file)}]
    assert record["command"].startswith("repnet adapt ") and str(tmp_path) not in record["command"]
    assert record["steps"] == 4 and record["poses"] == 270 and record["holdout_poses"] == 30
    figures = {"reprojection_px", "plausibility", "implausible_pct", "symmetry_mm", "bone_std_mm", "depth_mm"}
    figures |= {"jitter_mm", "plausible_lost_pct"}
    assert set(record["report"]["before"]) == figures
    lifter = load_lifter(Settings(model_path=out))  # the service's own loading and start-up check
    points = np.nan_to_num(np.load(poses_file)["keypoints"][:5]).astype(np.float32)
    prediction = lifter.lift(points, np.ones((5, 17), bool))
    assert lifter.info.model_id == "mine" and np.isfinite(prediction.pose_3d).all()
    assert "adapted by `repnet adapt`" in lifter.info.training_method  # GET /v1/model says so


def test_adapt_resumes_bit_for_bit(poses_file: Path, parent: Path, tmp_path: Path) -> None:
    straight, halves = tmp_path / "straight", tmp_path / "halves"
    # 20 critic-only steps (the warm-up), then both networks; the first half ends inside the warm-up.
    run = ["--run-dir", str(straight), "--force"]
    assert adapt(poses_file, parent, tmp_path / "a.onnx", "--steps", "23", *run) == 0
    run = ["--run-dir", str(halves), "--force"]
    assert adapt(poses_file, parent, tmp_path / "b.onnx", "--steps", "10", *run) == 0
    assert adapt(poses_file, parent, tmp_path / "b.onnx", "--steps", "23", "--resume", *run) == 0
    one, two = (torch.load(d / "adapt.pt", weights_only=False) for d in (straight, halves))
    assert one["step"] == two["step"] == 23
    for part in ("generator", "critic", "opt_g"):
        flat_one = torch.nn.utils.parameters_to_vector([t for t in _tensors(one["trainer"][part])])
        flat_two = torch.nn.utils.parameters_to_vector([t for t in _tensors(two["trainer"][part])])
        assert torch.equal(flat_one, flat_two), part
    parent_weights = checkpoint.load(parent)["generator"]
    trained = two["trainer"]["generator"]
    assert any(not torch.equal(trained[k], v) for k, v in parent_weights.items())  # it did train


def _tensors(state: object) -> list[torch.Tensor]:
    """Every tensor of a (nested) state dict, in a fixed order."""
    if isinstance(state, torch.Tensor):
        return [state.flatten().double()]
    if isinstance(state, dict):
        return [t for k in sorted(state, key=str) for t in _tensors(state[k])]
    if isinstance(state, (list, tuple)):
        return [t for item in state for t in _tensors(item)]
    return []


def test_resume_with_other_settings_is_refused(
    poses_file: Path, parent: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = ["--run-dir", str(tmp_path / "run"), "--force"]
    assert adapt(poses_file, parent, tmp_path / "a.onnx", "--steps", "2", *run) == 0
    assert (
        adapt(poses_file, parent, tmp_path / "a.onnx", "--steps", "4", "--seed", "1", "--resume", *run) == 2
    )
    assert "seed=0" in capsys.readouterr().err


def test_resume_refuses_a_planted_checkpoint_and_runs_nothing_from_it(
    poses_file: Path, parent: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = ["--run-dir", str(tmp_path / "run"), "--force"]
    assert adapt(poses_file, parent, tmp_path / "a.onnx", "--steps", "2", *run) == 0
    marker = tmp_path / "ran"
    plant((tmp_path / "run").rglob("adapt.pt").__next__(), marker)
    assert adapt(poses_file, parent, tmp_path / "b.onnx", "--steps", "4", "--resume", *run) == 2
    assert "refused, it holds more than tensors" in capsys.readouterr().err
    assert not marker.exists() and not (tmp_path / "b.onnx").exists()


def test_a_worse_model_is_not_written_unless_forced(
    poses_file: Path, parent: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    # Any change at all counts as worse: the adapted model cannot pass.
    monkeypatch.setattr(adapt_report, "TOLERANCE", dict.fromkeys(adapt_report.TOLERANCE, -1e9))
    out = tmp_path / "worse.onnx"
    assert adapt(poses_file, parent, out, "--steps", "2", "--run-dir", str(tmp_path / "run")) == 1
    assert not out.exists() and "not written" in capsys.readouterr().err
    assert adapt(poses_file, parent, out, "--steps", "2", "--run-dir", str(tmp_path / "run"), "--force") == 0
    assert json.loads(read_metadata(out)["lineage"])["refused_but_forced"]


def test_worse_names_each_figure_that_got_worse_the_furthest_first() -> None:
    before = Figures(10.0, 0.7, 2.0, 5.0, 3.0, depth_mm=100.0, jitter_mm=4.0)
    # a mean nearer 0.5, more implausible answers and a few lost plausible ones are no sign alone
    assert worse(before, Figures(10.9, 0.4, 9.9, 5.9, 3.9, 140.0, 4.9, plausible_lost_pct=40.0)) == []
    found = worse(before, Figures(11.5, 0.7, 3.5, 7.0, 4.5, 60.0, 6.0, plausible_lost_pct=60.0))
    unordered = replace(before, jitter_mm=90.0)  # not a sequence: its jitter is not judged
    assert worse(unordered, replace(unordered, jitter_mm=200.0)) == []
    order = ["symmetry", "jitter", "reprojection", "bone-length", "parent's", "depth"]  # by excess
    assert [r.split()[0] for r in found] == order
    assert "(at most 50 %)" in found[4] and "0.60x the parent's" in found[5]


class DepthScaled(torch.nn.Module):
    """A generator whose every answer has its depth multiplied by `factor` and its camera divided by
    it: the same reprojection K X, a flipped (-1), flattened or stretched person."""

    def __init__(self, generator: RepNet, factor: float) -> None:
        super().__init__()
        self.generator, self.scale = generator, torch.tensor([1.0, 1.0, factor])

    def forward(self, points: torch.Tensor, visible: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pose, camera = self.generator(points, visible)
        return pose * self.scale, camera / self.scale


@pytest.mark.parametrize(
    ("factor", "decided"),
    [(-1.0, "parent's plausible answers lost"), (0.2, "symmetry error"), (1.0, None)],
)
def test_a_depth_flipped_or_collapsed_model_is_refused_though_it_reprojects_the_same(
    poses_file: Path, parent: Path, factor: float, decided: str | None
) -> None:
    state = checkpoint.from_onnx(parent)
    scorer = adapt_report.parent_scorer(state, state["metadata"])
    generator = generator_of(state)
    points = np.load(poses_file)["keypoints"].astype(np.float32)
    visible = np.isfinite(points).all(axis=-1).astype(np.float32)
    held = (np.nan_to_num(points), visible)
    broken = DepthScaled(generator, factor).eval()
    before, was = adapt_report.answers(generator, scorer, *held, True, runs=[150, 150])
    after = adapt_report.adapted_figures(was, broken, scorer, held, True, runs=[150, 150])
    assert after.reprojection_px == pytest.approx(before.reprojection_px, rel=1e-4)
    reasons = worse(before, after)
    if decided is None:
        assert reasons == [] and after.plausible_lost_pct == 0.0
        return
    assert reasons and reasons[0].startswith(decided), reasons
    if factor < 0:  # the flip: only the parent's plausibility sees it
        assert len(reasons) == 1 and after.plausible_lost_pct > 90.0
    else:
        assert any(r.startswith("depth extent") and "0.20x" in r for r in reasons)


def test_the_command_refuses_a_depth_flipped_adaptation_and_says_why(
    poses_file: Path, parent: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    run = Adaptation.run

    def flipped(self: Adaptation, *args: object, **kwargs: object) -> bool:
        """Adapt, then flip the generator's depth in its weights: z of the pose and K's third column."""
        done = run(self, *args, **kwargs)  # type: ignore[arg-type]
        with torch.no_grad():
            last_pose = self.trainer.generator.pose_branch[-1]
            last_camera = self.trainer.generator.camera_branch[-1]
            for layer, rows in ((last_pose, slice(2, None, 3)), (last_camera, [2, 5])):
                layer.weight[rows] *= -1
                layer.bias[rows] *= -1
        return done

    monkeypatch.setattr(Adaptation, "run", flipped)
    out = tmp_path / "flipped.onnx"
    assert adapt(poses_file, parent, out, "--steps", "2", "--run-dir", str(tmp_path / "run")) == 1
    err = capsys.readouterr().err
    assert not out.exists()
    assert "not written" in err and "parent's plausible answers lost" in err, err


def test_without_steps_clips_get_the_short_run_and_spread_poses_the_long_one() -> None:
    figures = Figures(
        reprojection_px=5.0, plausibility=0.5, implausible_pct=1.0, symmetry_mm=5.0, bone_std_mm=2.0
    )
    clip = replace(figures, jitter_mm=34.0)
    spread = replace(figures, jitter_mm=89.0)
    assert adapt_report.default_steps(clip, 32)[0] == adapt_report.STEPS_FOR_CLIPS == 500
    assert adapt_report.default_steps(spread, 32)[0] == adapt_report.STEPS_FOR_SPREAD == 2000
    assert adapt_report.default_steps(clip, 2)[0] == 2000  # runs too short to be clips
    assert "34.0 mm / pose^2" in adapt_report.default_steps(clip, 32)[1]


def test_the_command_chooses_its_steps_from_the_held_out_2d_and_says_why(
    poses_file: Path, parent: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    monkeypatch.setattr(Adaptation, "run", lambda *_args, **_kwargs: True)  # the choice, not the training
    clip = np.concatenate([_example_clip()] * 3)  # 120 frames of a slow turn
    clip_file = tmp_path / "clip.npz"
    np.savez(clip_file, keypoints=clip, format="h36m17", frame=np.arange(len(clip)))
    chosen = {}
    for name, source in (("clip", clip_file), ("spread", poses_file)):
        out = tmp_path / f"{name}.onnx"
        assert adapt(source, parent, out, "--run-dir", str(tmp_path / name), "--force") == 0
        err = capsys.readouterr().err
        chosen[name] = json.loads(read_metadata(out)["lineage"])["config"]["steps"]
        assert f"{chosen[name]} steps: the held-out 2D are" in err, err
    assert chosen == {"clip": 500, "spread": 2000}
    assert (
        adapt(
            poses_file,
            parent,
            tmp_path / "given.onnx",
            "--steps",
            "7",
            "--run-dir",
            str(tmp_path / "g"),
            "--force",
        )
        == 0
    )
    assert "steps: the held-out" not in capsys.readouterr().err


def test_the_caches_checkpoint_goes_on_success_and_stays_named_on_refusal_or_interruption(
    poses_file: Path, parent: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:  # fmt: skip
    monkeypatch.setenv(lineage.CACHE_ENV, str(tmp_path / "cache"))
    runs = tmp_path / "cache" / "adapt"
    out = tmp_path / "mine.onnx"
    assert adapt(poses_file, parent, out, "--steps", "2", "--force") == 0
    assert out.is_file() and not list(runs.rglob("adapt.pt"))  # written: nothing left behind
    monkeypatch.setattr(adapt_report, "TOLERANCE", dict.fromkeys(adapt_report.TOLERANCE, -1e9))
    assert adapt(poses_file, parent, tmp_path / "worse.onnx", "--steps", "2") == 1
    err = capsys.readouterr().err
    (state,) = runs.rglob("adapt.pt")
    size = f"({state.stat().st_size / 1e6:.1f} MB)"
    assert f"its checkpoint is kept in {state} {size}: --resume --force writes it" in err
    assert "only 30 held-out poses: the decision needs at least 100" in err
    assert "give about 1000 poses (1000 frames of one person, 33 s at 30 fps)" in err
    assert adapt(poses_file, parent, tmp_path / "worse.onnx", "--steps", "2", "--resume", "--force") == 0
    assert "at step 2 of 2" in capsys.readouterr().err and not list(runs.rglob("adapt.pt"))

    def interrupted(*_args: object, **_kwargs: object) -> bool:
        raise KeyboardInterrupt

    monkeypatch.setattr(adapt_cli.Adaptation, "run", interrupted)
    assert adapt(poses_file, parent, tmp_path / "c.onnx", "--steps", "2") == 130
    assert "interrupted; no checkpoint was written yet" in capsys.readouterr().err


def test_more_data_is_asked_for_below_the_refusals_minimum() -> None:
    assert adapt_report.MIN_HOLDOUT == 100  # one pose of 100 moves a share by a point
    said = adapt_cli.more_data(3, 0.1)
    assert said is not None and said.startswith("only 3 held-out poses: the decision needs at least 100")
    assert "moves a share by 33 points, not at most 1" in said and "give about 1000 poses" in said
    assert "give about 400 poses" in str(adapt_cli.more_data(5, 0.25))
    assert adapt_cli.more_data(100, 0.1) is None


def test_bad_flags_are_named(
    poses_file: Path, parent: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        adapt(poses_file, parent, tmp_path / "a.onnx", "--holdout-fraction", "1.5")
    assert exit_info.value.code == 2 and "--holdout-fraction" in capsys.readouterr().err
    assert adapt(poses_file, parent, tmp_path / "a.json") == 2
    assert ".onnx" in capsys.readouterr().err
    flags = [("--minutes", "nan"), ("--minutes", "inf"), ("--confidence-threshold", "-1"),
             ("--confidence-threshold", "2"), ("--confidence-threshold", "nan"), ("--model-id", "a b"),
             ("--model-id", "<x>")]  # fmt: skip
    for flag, value in flags:
        with pytest.raises(SystemExit) as exit_info:
            adapt(poses_file, parent, tmp_path / "a.onnx", flag, value)
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and flag in err and repr(value) in err, (flag, value, err)
    assert adapt(poses_file, parent, tmp_path / "missing" / "a.onnx") == 2  # before any training
    assert "does not exist" in capsys.readouterr().err
    assert adapt(poses_file, parent, tmp_path / "my model.onnx") == 2  # its name is no model id
    assert "--model-id" in capsys.readouterr().err


def test_the_lineage_names_no_path_of_the_machine_quoted_or_not(
    poses_file: Path, parent: Path, tmp_path: Path
) -> None:
    folder = tmp_path / "my models"  # a space: the command line quotes it
    folder.mkdir()
    out = folder / "mine.onnx"
    flags = ["--steps", "1", "--run-dir", str(tmp_path / "a run"), "--force", "--model-id", "mine"]
    assert adapt(poses_file, parent, out, *flags) == 0
    meta = read_metadata(out)
    assert str(tmp_path) not in meta["lineage"] and "/tmp" not in meta["lineage"], meta["lineage"]
    assert "mine.onnx" in json.loads(meta["lineage"])["command"]


def test_holdout_is_the_tail_of_each_input() -> None:
    held = split_holdout([10, 5, 1], 0.2)
    assert held.tolist() == [False] * 8 + [True] * 2 + [False] * 4 + [True] + [False]
    assert not split_holdout([10], 0.0).any()


def test_residuals_are_the_input_minus_the_reprojection_and_zero_at_hidden_joints() -> None:
    torch.manual_seed(0)
    generator = RepNet(RepNetConfig(width=32)).eval()
    rng = np.random.default_rng(0)
    points = (rng.normal(size=(8, 17, 2)) * 80 + 400).astype(np.float32)
    visible = (rng.random((8, 17)) > 0.2).astype(np.float32)
    pose, camera, residual = answer(generator, points, visible, mirror_average=False)
    with torch.no_grad():
        w = normalize_keypoints(torch.from_numpy(points), torch.from_numpy(visible))
        x, k = generator(w, torch.from_numpy(visible))
        expected = (w - masked_centre(project_weak_perspective(k, x), torch.from_numpy(visible))).numpy()
    assert np.allclose(pose, x.numpy() * MM_PER_UNIT, atol=1e-3)
    assert np.allclose(residual[visible > 0], expected[visible > 0], atol=1e-5)
    assert (residual[visible == 0] == 0).all()


def test_prior_poses_are_whole_people() -> None:
    model = prior.PosePrior.load()
    poses = model.sample(2000, np.random.default_rng(0))
    assert poses.shape == (2000, skeleton.NUM_JOINTS, 3) and np.isfinite(poses).all()
    assert metrics.symmetry_error(poses).max() < 0.05  # mm: a left limb as long as the right one
    lengths = np.linalg.norm(poses[:, 1:] - poses[:, list(skeleton.PARENTS[1:])], axis=-1)
    ratio = lengths / model.mean_lengths
    assert 0.7 < ratio.min() and ratio.max() < 1.4
    assert np.median(poses[:, 10, 2] - poses[:, 3, 2]) > 1000  # head above ankle: Z up, standing


def test_a_fitted_prior_round_trips_and_keeps_the_bone_lengths(tmp_path: Path) -> None:
    poses = prior.PosePrior.load().sample(600, np.random.default_rng(4))
    fitted = prior.fit(poses, components=2, dims=6)
    fitted.save(tmp_path / "prior.npz")
    again = prior.PosePrior.load(tmp_path / "prior.npz")
    assert "research" in str(np.load(tmp_path / "prior.npz")["licence"])
    assert np.allclose(again.mean_lengths, fitted.mean_lengths, rtol=1e-6)
    lengths = np.linalg.norm(poses[:, 1:] - poses[:, list(skeleton.PARENTS[1:])], axis=-1)
    assert np.allclose(again.mean_lengths, lengths.mean(axis=0), rtol=1e-3)
    drawn = again.sample(50, np.random.default_rng(5))
    assert drawn.shape == (50, skeleton.NUM_JOINTS, 3) and metrics.symmetry_error(drawn).max() < 0.05


def test_an_adapted_model_keeps_the_temporal_models_of_its_parent(
    poses_file: Path, parent: Path, tmp_path: Path
) -> None:
    from tests.service.test_temporal import clip, temporal_service

    out = tmp_path / "adapted-here.onnx"
    assert adapt(poses_file, parent, out, "--steps", "4", "--run-dir", str(tmp_path / "run"), "--force") == 0
    settings = Settings(model_path=out, grpc_port=0, intra_op_threads=1)
    lifter = load_lifter(settings)
    service = temporal_service(lifter, settings)  # its temporal models load over the adapted model
    temporal = next(service)
    try:
        points = clip(30, noise_px=2.0)
        poses = [{"keypoints": p.tolist(), "track_id": "a", "frame": f} for f, p in enumerate(points)]
        for mode in ("causal", "offline"):
            reply = temporal.client.post("/lift", json={"poses": poses, "temporal": mode, "fps": 30.0})
            assert reply.status_code == 200, reply.text
            assert all(p["temporal"] for p in reply.json()["poses"])
        listed = temporal.client.get("/v1/models").json()["models"]
        assert listed[0]["model_id"] == "adapted-here" and listed[0]["temporal"]
        assert sorted(listed[0]["temporal_models"]) == sorted(
            e.lifter.model_id for e in temporal.models.engines.values()
        )
    finally:
        service.close()
    other = tmp_path / "unrelated.onnx"  # the same weights without the lineage: not its parent's child
    meta = read_metadata(out)
    model = onnx.load(out)
    del model.metadata_props[:]
    for key, value in meta.items():
        if key != "lineage":
            model.metadata_props.add(key=key, value=value)
    onnx.save(model, other)
    assert load_temporal_lifters(other, load_lifter(Settings(model_path=other)), TEMPORAL_PATHS) == {}


def test_triplets_are_three_consecutive_frames_of_one_person() -> None:
    previous = np.array([-1, 0, 1, 2, -1, 4, -1])  # a run of 4, a run of 2, a lone frame
    assert triplets_of(previous).tolist() == [[0, 1, 2], [1, 2, 3]]
    assert triplets_of(np.full(3, -1)).shape == (0, 3)


def test_camera_frame_turns_a_pose_by_the_rotation_in_k() -> None:
    angle = 0.7
    c, s = float(np.cos(angle)), float(np.sin(angle))
    rotation = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    pose = torch.randn(1, 17, 3, generator=torch.Generator().manual_seed(0))
    camera = 2.5 * rotation[None, :2]
    assert torch.allclose(camera_frame(pose, camera), pose @ rotation.T, atol=1e-6)


def _clip_adaptation(points: np.ndarray, weight: float, previous: np.ndarray | None) -> Adaptation:
    state = checkpoint.from_onnx(Settings().model_path)
    visible = np.ones(points.shape[:2], np.float32)
    config = replace(
        AdaptConfig(), steps=3, critic_warmup=1, batch_size=16, prior_poses=500, smoothness_weight=weight
    )
    adaptation = Adaptation(config, state, points, visible, mirror_average=True, threads=1, previous=previous)
    adaptation.trainer.config = replace(adaptation.trainer.config, smoothness_batch=8)
    return adaptation


def test_the_smoothness_term_is_zero_on_a_still_clip_and_grows_with_its_jitter() -> None:
    still = np.repeat(_example_clip()[:1], 12, axis=0)
    jitter = np.random.default_rng(0).normal(0.0, 6.0, still.shape).astype(np.float32)
    previous = np.arange(-1, 11)
    terms = {}
    for name, points in (("still", still), ("jittered", still + jitter)):
        adaptation = _clip_adaptation(points, 1.0, previous)
        torch.manual_seed(0)
        with torch.no_grad():
            terms[name] = float(adaptation.trainer.smoothness_term())
    assert terms["still"] < 1e-6 < 1e-3 < terms["jittered"]


def test_adapt_trains_on_the_smoothness_of_the_clips_only_when_asked() -> None:
    clip = _example_clip()
    seen: dict[str, list[float]] = {}
    for name, weight, previous in (
        ("smooth", 1.0, np.arange(-1, len(clip) - 1)),
        ("off", 0.0, np.arange(-1, len(clip) - 1)),
        ("no clips", 1.0, None),
    ):
        adaptation = _clip_adaptation(clip, weight, previous)
        got: list[float] = []
        adaptation.run(0, None, on_step=lambda _step, terms, got=got: got.append(terms["smooth"].item()))
        seen[name] = got
    assert seen["smooth"][0] == 0.0 and min(seen["smooth"][1:]) > 0.0  # after the critic's warm-up
    assert seen["off"] == seen["no clips"] == [0.0, 0.0, 0.0]


def _example_clip() -> np.ndarray:
    """(40, 17, 2) px: a prior pose turning slowly about the vertical before a fixed camera."""
    world = prior.PosePrior.load().sample(1, np.random.default_rng(5))[0]  # (J, 3) mm, Z up
    turns = np.linspace(0.0, 0.6, 40)
    x = world[:, 0] * np.cos(turns)[:, None] - world[:, 1] * np.sin(turns)[:, None]
    return np.stack([500.0 + 0.3 * x, 500.0 - 0.3 * np.broadcast_to(world[:, 2], x.shape)], -1).astype(
        np.float32
    )


def test_adapt_draws_its_3d_poses_from_the_prior_it_is_given(
    poses_file: Path,
    parent: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    shipped = prior.PosePrior.load()
    giant = prior.fit(shipped.sample(600, np.random.default_rng(6)) * 1.5, components=2, dims=6)
    giant.save(tmp_path / "giant.npz")
    drawn: list[np.ndarray] = []
    real_init = Adaptation.__init__

    def spy(self: Adaptation, *args: object, **kwargs: object) -> None:
        real_init(self, *args, **kwargs)  # type: ignore[arg-type]
        drawn.append(self.trainer.pool.poses_world)

    monkeypatch.setattr(Adaptation, "__init__", spy)
    out = tmp_path / "giant.onnx"
    assert (
        adapt(poses_file, parent, out, "--steps", "1", "--force", "--prior", str(tmp_path / "giant.npz")) == 0
    )
    legs = np.linalg.norm(drawn[0][:, 2] - drawn[0][:, 1], axis=-1)  # right thigh, mm
    assert np.median(legs) > 1.3 * shipped.mean_lengths[1]
    record = json.loads(read_metadata(out)["lineage"])
    assert record["prior"] == {"sha256": lineage.file_sha256(tmp_path / "giant.npz")}
    (tmp_path / "not.npz").write_bytes(b"no prior")
    assert adapt(poses_file, parent, tmp_path / "b.onnx", "--prior", str(tmp_path / "not.npz")) == 2
    assert "--prior" in capsys.readouterr().err and not (tmp_path / "b.onnx").exists()


def test_the_command_says_whether_the_bundled_temporal_models_run_over_the_adapted_model(
    parent: Path, tmp_path: Path
) -> None:
    bundled = read_metadata(parent)
    sha = lineage.file_sha256(parent)
    assert adapt_cli.keeps_temporal(sha, bundled)  # v7: their base
    child = {"lineage": json.dumps({"parent": {"sha256": sha}})}  # adapted from v7, adapted again
    assert adapt_cli.keeps_temporal("0" * 64, child)
    assert not adapt_cli.keeps_temporal("0" * 64, {})  # another parent (a no-sitting one)
