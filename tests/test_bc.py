"""BC trainer: data loading, networks, ensembles, both regimes, resume after a kill, CLI errors."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from shiftkit.datasets.errors import ConfigError, DatasetError, ShiftkitError
from shiftkit.policies.bc_policy import BCPolicy, Normalization, PolicySpec, load_policy
from shiftkit.policies.networks import KeypointCNN, ResNet18Keypoints, SpatialSoftArgmax
from shiftkit.policies.run_dir import checkpoint_bytes, load_checkpoint
from shiftkit.policies.trainers.bc.args import BCArgs
from shiftkit.policies.trainers.bc.training import train, update_members


def make_dataset(
    root: Path,
    episodes: int = 8,
    length: int = 25,
    image: str | None = None,
    learnable: bool = True,
    depth: str | None = None,
    seed: int = 0,
    still_std: float | None = None,
) -> Path:
    """A tiny LeRobot dataset written by lerobot's own writer. State-only: action = linear function
    of the state (`still_std`: s3, which the action ignores, is ~0 with this std, like the velocity of
    an object no demonstration touches). `image="image"|"video"`: a bright square whose position is the action (`depth`
    "m" or "mm": plus a lerobot depth map of it, float32 metres or uint16 millimetres)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(seed)
    features = {
        "observation.state": {"dtype": "float32", "shape": (4,), "names": ["s0", "s1", "s2", "s3"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["a0", "a1"]},
    }
    if image:
        features["observation.images.front"] = {
            "dtype": image,
            "shape": (48, 64, 3),
            "names": ["height", "width", "channels"],
        }
    if depth:
        features["observation.depth.front"] = {
            "dtype": "image",
            "shape": (48, 64, 1),
            "names": ["height", "width", "channels"],
            "info": {"is_depth_map": True},
        }
    ds = LeRobotDataset.create("test/bc", fps=10, root=root, features=features, use_videos=image == "video")
    for _ in range(episodes):
        for _ in range(length):
            s = rng.normal(size=4).astype(np.float32)
            if still_std is not None:
                s[3] = rng.normal(scale=still_std)
            a = np.array([s[0] + 0.5 * s[1], -s[2]], np.float32) if learnable else rng.normal(size=2).astype(np.float32)
            frame = {"observation.state": s, "task": "synthetic"}
            if image:
                x, y = int(rng.integers(6, 58)), int(rng.integers(6, 42))
                img = np.full((48, 64, 3), 20, np.uint8)
                img[y - 4 : y + 4, x - 4 : x + 4] = 235
                frame["observation.images.front"] = img
                if depth:
                    metres = np.where(img[..., :1] > 100, 0.5, 1.5).astype(np.float32)
                    mm = np.rint(metres * 1000).astype(np.uint16)
                    frame["observation.depth.front"] = mm if depth == "mm" else metres
                a = np.array([x / 32 - 1, y / 24 - 1], np.float32)
            frame["action"] = a
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return root


@pytest.fixture(scope="module")
def state_ds(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("data") / "state")


def small_args(ds: Path, out: Path, **kw) -> BCArgs:
    base = dict(
        datasets=[str(ds)],
        output_dir=str(out),
        regime="fixed",
        steps=200,
        ensemble_size=2,
        hidden=[32, 32],
        batch_size=32,
        log_every=20,
        checkpoint_every=50,
        device="cpu",
    )
    return BCArgs(**{**base, **kw})


def metric_lines(run: Path, split: str) -> list[dict]:
    return [m for m in map(json.loads, (run / "metrics.jsonl").read_text().splitlines()) if m["split"] == split]


# ------------------------------------------------------------------------------ data


@pytest.mark.parametrize("kind", ["image", "video"])
def test_frame_table_matches_lerobot_reader(tmp_path, kind):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.policies.data import FrameTable

    root = make_dataset(tmp_path / kind, episodes=3, length=6, image=kind)
    ds = LeRobotDataset("test/bc", root=root, video_backend="pyav")
    table = FrameTable([ds, ds], ["observation.state", "observation.images.front", "action"])
    assert table.num_frames == 36 and table.episodes[:2] == [(0, 6), (6, 12)] and len(table.episodes) == 6
    rows = np.array([17, 0, 5, 18, 35])
    batch = table.gather(rows)
    assert batch["observation.images.front"].dtype == np.uint8
    for i, row in enumerate(rows):
        item = ds[int(row % 18)]
        np.testing.assert_array_equal(batch["observation.state"][i], item["observation.state"].numpy())
        np.testing.assert_array_equal(batch["action"][i], item["action"].numpy())
        img = np.round(item["observation.images.front"].numpy().transpose(1, 2, 0) * 255)
        np.testing.assert_array_equal(batch["observation.images.front"][i], img)


def test_episode_split_is_seeded_and_by_episode(state_ds):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.policies.data import FrameTable

    table = FrameTable([LeRobotDataset("test/bc", root=state_ds)], ["action"])
    train_rows, val_rows = table.split_episodes(0.2, seed=3)
    assert len(val_rows) == 2 * 25 and len(train_rows) == 6 * 25
    assert not set(train_rows) & set(val_rows)
    assert np.array_equal(val_rows, table.split_episodes(0.2, seed=3)[1])
    assert all(r % 25 == 0 for r in val_rows[::25])  # whole episodes


# ------------------------------------------------------------------------------ networks


def test_spatial_soft_argmax_finds_the_peak():
    ssam = SpatialSoftArgmax(5, 7)
    fmap = torch.full((1, 2, 5, 7), -50.0)
    fmap[0, 0, 0, 6] = 50.0  # top right
    fmap[0, 1, 4, 0] = 50.0  # bottom left
    kp = ssam(fmap)
    torch.testing.assert_close(kp, torch.tensor([[[1.0, -1.0], [-1.0, 1.0]]]), atol=1e-4, rtol=0)


def test_cnn_and_resnet_keypoint_shapes_and_range(tmp_path):
    images = torch.rand(3, 3, 48, 64) * 4 - 2
    cnn = KeypointCNN(3, 48, 64, num_keypoints=16)
    kp = cnn.keypoints(images)
    assert kp.shape == (3, 16, 2) and cnn(images).shape == (3, 32)
    assert kp.abs().max() <= 1.0
    resnet = ResNet18Keypoints(4, 48, 64, num_keypoints=8)
    out = resnet(torch.rand(2, 4, 48, 64))
    assert out.shape == (2, 16) and out.abs().max() <= 1.0

    from torchvision.models import resnet18

    weights = tmp_path / "resnet18.pt"
    torch.save(resnet18(weights=None).state_dict(), weights)
    loaded = ResNet18Keypoints(3, 48, 64, weights=weights)
    torch.testing.assert_close(loaded.trunk[0].weight, torch.load(weights)["conv1.weight"])
    first = KeypointCNN(3, 48, 64, weights=weights)
    torch.testing.assert_close(first.conv1.weight, torch.load(weights)["conv1.weight"])
    with pytest.raises(ConfigError, match="not found"):
        KeypointCNN(3, 48, 64, weights=tmp_path / "missing.pt")


def _spec(ensemble: int) -> PolicySpec:
    return PolicySpec(
        features={"observation.state": {"dtype": "float32", "shape": [4], "names": ["a", "b", "c", "d"]}},
        action={"dtype": "float32", "shape": [2], "names": ["x", "y"]},
        stats={
            "observation.state": {"mean": [0.0] * 4, "std": [1.0] * 4},
            "action": {"mean": [1.0, -1.0], "std": [2.0, 0.5]},
        },
        encoder="cnn",
        num_keypoints=8,
        hidden=[16],
        ensemble_size=ensemble,
    )


def test_ensemble_mean_and_spread():
    policy = BCPolicy(_spec(3), seed=1)
    batch = {"observation.state": torch.randn(5, 4)}
    outs = policy.member_outputs(batch)
    assert outs.shape == (3, 5, 2)
    assert not torch.allclose(outs[0], outs[1])  # members start different
    torch.testing.assert_close(policy(batch), outs.mean(0))
    torch.testing.assert_close(policy.spread(batch), outs.var(0).norm(dim=-1))
    assert (policy.spread(batch) > 0).all()
    for m in policy.members[1:]:
        m.load_state_dict(policy.members[0].state_dict())
    assert torch.allclose(policy.spread(batch), torch.zeros(5))
    assert BCPolicy(_spec(3), seed=1).state_dict().keys() == policy.state_dict().keys()
    torch.testing.assert_close(
        BCPolicy(_spec(3), seed=1).members[2].head[0].weight, BCPolicy(_spec(3), seed=1).members[2].head[0].weight
    )


# ------------------------------------------------------------------------------ training


def test_fixed_regime_learns_and_writes_run(state_ds, tmp_path):
    out = tmp_path / "run"
    metrics = train(small_args(state_ds, out, steps=300, val_fraction=0.25))
    train_loss = [m["loss"] for m in metric_lines(out, "train")]
    assert train_loss[-1] < 0.2 * train_loss[0]
    assert [m["lr"] for m in metric_lines(out, "train")][-1] == pytest.approx(3e-4 / 2)  # halved midway
    assert metrics["val_loss"] < 0.3 and metrics["steps"] == 300  # normalised units: 1 = predicting the mean
    config = json.loads((out / "config.json").read_text())
    assert config["trainer"] == "bc" and config["args"]["weight_decay"] == 0.1
    assert config["datasets"][0]["fingerprint"] and config["versions"]["lerobot"]
    assert (out / "README.md").read_text().strip()
    assert (out / "checkpoints" / "last.txt").read_text() == "step-00000300.safetensors"
    assert len(list((out / "checkpoints").glob("step-*.safetensors"))) == 2  # keep=2

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    policy = load_policy(out)
    frame = LeRobotDataset("test/bc", root=state_ds)[7]
    action = policy.act({"observation.state": frame["observation.state"].numpy()})
    assert action.shape == (2,) and np.abs(action - frame["action"].numpy()).max() < 0.5


def test_early_stopping_stops_members_and_keeps_best(tmp_path):
    ds = make_dataset(tmp_path / "noise", episodes=6, length=20, learnable=False)
    out = tmp_path / "run"
    metrics = train(
        small_args(
            ds,
            out,
            regime="early-stop",
            steps=None,
            max_epochs=100,
            patience=3,
            hidden=[64, 64],
            batch_size=16,
            log_every=1000,
        )
    )
    val = metric_lines(out, "val")
    assert val[-1]["active"] == 0 and len(val) < 100  # every member stopped before max_epochs
    best = [min(m["member_loss"][i] for m in val) for i in range(2)]
    assert metrics["val_member_loss"] == pytest.approx(best)  # best weights restored
    assert json.loads((out / "config.json").read_text())["args"]["lr"] == 1e-3


@pytest.mark.parametrize("unit", ["m", "mm"])
def test_image_policy_trains_end_to_end(tmp_path, unit):
    """RGB + depth (float32 metres or uint16 millimetres, as lerobot records them): the trainer takes
    depth, and its statistics, in metres."""
    ds = make_dataset(tmp_path / "img", episodes=4, length=16, image="image", depth=unit)
    out = tmp_path / "run"
    train(
        small_args(
            ds,
            out,
            steps=60,
            ensemble_size=1,
            batch_size=16,
            num_keypoints=8,
            hidden=[64, 64],
            lr=1e-3,
            log_every=10,
            checkpoint_every=60,
        )
    )
    loss = [m["loss"] for m in metric_lines(out, "train")]
    assert loss[-1] < 0.6 * loss[0], loss
    policy = load_policy(out)
    assert policy.spec.image_keys() == ["observation.images.front", "observation.depth.front"]
    assert len(policy.members[0].encoders) == 2
    depth_mean = policy.normalizer._ms("observation.depth.front")[0]
    assert depth_mean.shape == (1, 1, 1, 1) and 0.5 < depth_mean.item() < 1.5
    img = np.zeros((48, 64, 3), np.uint8)
    batch = {
        "observation.images.front": torch.from_numpy(img)[None],
        "observation.state": torch.zeros(1, 4),
        "observation.depth.front": torch.ones(1, 48, 64, 1),
    }
    obs = policy.normalizer(batch)
    kp = policy.members[0].encoders[0].keypoints(obs["observation.images.front"])
    assert kp.shape == (1, 8, 2) and kp.abs().max() <= 1.0
    assert policy.act({k: v[0].numpy() for k, v in batch.items()}).shape == (2,)


def test_resume_after_kill_equals_uninterrupted_run(state_ds, tmp_path):
    killed, clean = tmp_path / "killed", tmp_path / "clean"
    cli = [
        sys.executable,
        "-m",
        "shiftkit.app.cli",
        "train",
        "bc",
        "--dataset",
        str(state_ds),
        "--output",
        str(killed),
        "--regime",
        "fixed",
        "--steps",
        "3000",
        "--ensemble",
        "2",
        "--hidden",
        "32,32",
        "--batch-size",
        "32",
        "--log-every",
        "20",
        "--checkpoint-every",
        "100",
        "--device",
        "cpu",
    ]
    proc = subprocess.Popen(
        cli, env={**os.environ, "PYTHONUNBUFFERED": "1"}, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    last = killed / "checkpoints" / "last.txt"
    deadline = time.time() + 120
    while not last.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()
    state = load_checkpoint(killed / "checkpoints" / last.read_text())
    assert not state["final"] and state["step"] < 3000  # really killed mid-run

    args = small_args(state_ds, killed, steps=3000, checkpoint_every=100)
    train(BCArgs(**{**args.__dict__, "resume": True}))
    train(small_args(state_ds, clean, steps=3000, checkpoint_every=100))
    a, b = load_policy(killed).state_dict(), load_policy(clean).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    strip = lambda lines: [{k: v for k, v in m.items() if k != "steps_per_s"} for m in lines]  # noqa: E731
    assert strip(metric_lines(killed, "train")) == strip(metric_lines(clean, "train"))


def test_same_seed_same_checkpoint_bytes_in_fresh_processes(state_ds, tmp_path):
    """Each checkpoint holds the global torch generator, which a fresh process starts from a random seed:
    two processes with the same seed must still write the same bytes."""
    runs = [tmp_path / "a", tmp_path / "b"]
    for run in runs:
        subprocess.run(
            [sys.executable, "-m", "shiftkit.app.cli", "train", "bc", "--dataset", str(state_ds), "--output",
             str(run), "--regime", "fixed", "--steps", "60", "--hidden", "16,16", "--checkpoint-every", "30",
             "--device", "cpu", "--seed", "3", "--no-progress"],
            check=True, capture_output=True,
        )  # fmt: skip
    names = sorted(p.name for p in (runs[0] / "checkpoints").glob("*.safetensors"))
    assert names == sorted(p.name for p in (runs[1] / "checkpoints").glob("*.safetensors")) and len(names) >= 2
    for name in names:
        assert (runs[0] / "checkpoints" / name).read_bytes() == (runs[1] / "checkpoints" / name).read_bytes(), name


# ------------------------------------------------------------------------------ normalisation


def test_std_floor_is_relative_to_each_dimension():
    norm = Normalization()
    mean, std = torch.tensor([0.02, 1.0, 0.0, 0.0]), torch.tensor([2e-5, 0.5, 2e-5, 0.0])
    # nearly constant at 2 cm: floored at 1% of its size; a varying one untouched; ~0: the absolute floor
    torch.testing.assert_close(norm.floored(mean, std), torch.tensor([2e-4, 0.5, 2e-5, 1e-6]), rtol=1e-3, atol=0)
    with pytest.raises(ConfigError, match="norm_clip"):
        Normalization(clip=0)
    with pytest.raises(ConfigError, match="norm_std_floor"):
        BCArgs(datasets=["x"], output_dir="y", norm_std_floor=-1).resolved()


def test_correction_outside_few_demonstrations_stays_bounded(tmp_path):
    """5 demonstrations where s3 has std 2e-5 (an object nobody touched); a correction then moves it
    by 0.1: 5000 stds. Its normalised input, the policy's output and the BC loss stay bounded."""
    ds = make_dataset(tmp_path / "few", episodes=5, length=20, still_std=2e-5)
    out = tmp_path / "run"
    train(small_args(ds, out, steps=100, log_every=50, checkpoint_every=100))
    policy = load_policy(out)
    demo = {"observation.state": torch.tensor([[0.3, -0.2, 0.5, 0.0]])}
    correction = {"observation.state": torch.tensor([[0.3, -0.2, 0.5, 0.1]])}
    assert policy.normalizer(correction)["observation.state"].abs().max() <= 10.0
    # beyond the bound every state acts as the bound: the output cannot run away with the input
    far = {"observation.state": torch.tensor([[0.3, -0.2, 0.5, 1e3]])}
    torch.testing.assert_close(policy(far), policy(correction))
    a_mean, a_std = policy.normalizer._ms("action")
    assert ((policy(correction) - a_mean) / a_std).abs().max() < 50  # normalised action units
    # a BC update on the correction (labelled with the demonstration's action): bounded loss
    batch = {**correction, "action": policy(demo).detach()}
    optimizers = [torch.optim.Adam(m.parameters(), lr=1e-4) for m in policy.members]
    losses = update_members(policy, optimizers, {k: v.repeat(2, 1) for k, v in batch.items()}, 1, [True, True], 1e-4)
    assert max(losses) < 100, losses


def test_normalization_round_trips_and_is_on_the_card(state_ds, tmp_path):
    out = tmp_path / "run"
    train(small_args(state_ds, out, steps=20, norm_std_floor=0.05, norm_clip=4.0))
    state = load_checkpoint(out / "checkpoints" / "step-00000020.safetensors")
    assert state["policy_spec"]["normalization"] == {"std_floor": 0.05, "std_min": 1e-6, "clip": 4.0}
    policy = load_policy(out)
    assert policy.spec.normalization == Normalization(std_floor=0.05, clip=4.0) and policy.normalizer.clip == 4.0
    x = {"observation.state": torch.tensor([[100.0, 0.0, 0.0, 0.0]])}
    assert policy.normalizer(x)["observation.state"].max() == 4.0
    card = (out / "README.md").read_text()
    assert "## Input normalisation" in card and "0.05 x its RMS value" in card and "clipped to +-4 stds" in card
    assert "Dimensions normalised by a floored std: 0." in card  # every state dim varies (std ~1)
    assert "| `norm_clip` | `4.0` |" in card


def test_checkpoint_without_normalization_loads_with_its_legacy_behaviour(tmp_path):
    """Checkpoints from before the floor and clip: a std under 1e-6 became 1, nothing was clipped."""
    ds = make_dataset(tmp_path / "few", episodes=5, length=20, still_std=2e-5)
    out = tmp_path / "run"
    train(small_args(ds, out, steps=20))
    path = out / "checkpoints" / "step-00000020.safetensors"
    state = load_checkpoint(path)
    del state["policy_spec"]["normalization"]
    path.write_bytes(checkpoint_bytes(state))
    policy = load_policy(out)
    assert policy.spec.normalization is None and policy.normalizer.clip is None
    correction = {"observation.state": torch.tensor([[0.3, -0.2, 0.5, 0.1]])}
    assert policy.normalizer(correction)["observation.state"].abs().max() > 1e3  # unbounded, as trained
    legacy = BCPolicy(PolicySpec(**{**state["policy_spec"], "normalization": None}))
    std = legacy.normalizer._ms("observation.state")[1]
    assert std[3] == pytest.approx(state["policy_spec"]["stats"]["observation.state"]["std"][3])


# ------------------------------------------------------------------------------ user errors


def test_user_errors_are_one_line(state_ds, tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        train(small_args(tmp_path / "nowhere", tmp_path / "r0"))
    with pytest.raises(ConfigError, match="observation.nope"):
        train(small_args(state_ds, tmp_path / "r1", inputs=["observation.nope"]))
    with pytest.raises(ConfigError, match="regime"):
        train(small_args(state_ds, tmp_path / "r2", regime="forever"))
    # a run that fails to start leaves no folder behind that would block the corrected command
    assert not any((tmp_path / r).exists() for r in ("r0", "r1", "r2"))
    train(small_args(state_ds, tmp_path / "r3", steps=20))
    with pytest.raises(ShiftkitError, match="already holds a run"):
        train(small_args(state_ds, tmp_path / "r3", steps=20))
    with pytest.raises(ConfigError, match="different 'steps'"):
        train(small_args(state_ds, tmp_path / "r3", steps=40, resume=True))

    from shiftkit.app.cli import main

    assert main(["train", "bc", "--dataset", str(tmp_path / "nowhere"), "--output", str(tmp_path / "r4")]) == 2


def test_default_is_one_network_and_ensemble_is_an_option(state_ds, tmp_path):
    defaults = BCArgs(datasets=["x"], output_dir="y")
    assert defaults.ensemble_size == 1 and defaults.threads == 1  # one network, one CPU thread
    train(small_args(state_ds, tmp_path / "one", steps=5, ensemble_size=BCArgs.ensemble_size))
    assert len(load_policy(tmp_path / "one").members) == 1
    train(small_args(state_ds, tmp_path / "five", steps=5, ensemble_size=5))
    assert len(load_policy(tmp_path / "five").members) == 5


def test_bc_args_are_the_shared_settings_and_the_runs_inputs_and_outputs():
    """`BCArgs` adds the run's fields to `BCSettings` (what FIRE nests): every option keeps its help,
    the inherited ones too."""
    import dataclasses

    from shiftkit.datasets.dataclass_config import field_docs
    from shiftkit.policies.trainers.bc.args import BCSettings

    settings = [f.name for f in dataclasses.fields(BCSettings)]
    names = [f.name for f in dataclasses.fields(BCArgs)]
    assert names[: len(settings)] == settings and {"datasets", "output_dir", "seed", "resume"} <= set(names)
    docs = field_docs(BCArgs)
    assert all(docs.get(name) for name in names) and docs["hidden"].startswith("Widths of the fully connected")


def test_train_prints_no_video_backend_traceback(state_ds, tmp_path):
    """lerobot's reader, left to choose its video backend, tries torchcodec and logs its loader's
    traceback (~40 lines) where torchcodec cannot load FFmpeg: `train` chooses up front."""
    cli = [sys.executable, "-m", "shiftkit.app.cli", "train", "bc", "--dataset", str(state_ds)]
    cli += ["--output", str(tmp_path / "run"), "--regime", "fixed", "--steps", "2", "--hidden", "8"]
    proc = subprocess.run([*cli, "--no-progress", "--device", "cpu"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "torchcodec" not in proc.stderr, proc.stderr[-3000:]


def test_video_backend_is_chosen_without_a_traceback(monkeypatch, caplog):
    import ctypes.util
    import importlib.util

    from shiftkit.datasets import video

    video.decoder_backend.cache_clear()
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: object() if name == "torchcodec" else find_spec(name, *a)
    )
    monkeypatch.setitem(sys.modules, "torchcodec", None)  # installed, but its import raises ImportError
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None)  # no FFmpeg on the library path
    assert video.decoder_backend() == "pyav" and caplog.records == []
    video.decoder_backend.cache_clear()
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: f"lib{name}.so.59")  # FFmpeg, broken torchcodec
    assert video.decoder_backend() == "pyav"
    (record,) = caplog.records
    assert record.getMessage().startswith("torchcodec cannot load FFmpeg here (") and "\n" not in record.getMessage()
    video.decoder_backend.cache_clear()
