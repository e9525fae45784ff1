"""The training loop: outputs, learning, checkpoints, resume, divergence, collectors."""

from __future__ import annotations

import copy
import gc
import importlib.util
import io
import itertools
import json
import math
import os
import random
import re
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, make_dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
import torch
from conftest import assert_same_run, hide_module, run_weights
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Categorical
from torchrl.modules import ValueOperator
from torchrl.record.loggers import CSVLogger

from rl_pg.checkpoint import CheckpointError, load_checkpoint
from rl_pg.envs import GridWorldEnv
from rl_pg.models import mlp_actor, mlp_critic
from rl_pg.normalization import PopArt, RunningNorm, update_running_norms
from rl_pg.recipes import load
from rl_pg.training import (
    Callback,
    RunDirBusy,
    RunDirUnusable,
    TrainConfig,
    TrainingDiverged,
    load_models,
    read_run,
    train,
)
from rl_pg.training.checkpoints import resolve_latest
from rl_pg.training.console import Console
from rl_pg.training.curves import read_curve
from rl_pg.training.loggers import BufferedCSVLogger
from rl_pg.training.metrics import EpisodeReturns
from rl_pg.training.optimisation import make_loss, make_optimizer, update
from rl_pg.training.seeds import evaluation_seed
from rl_pg.training.settings import BatchedEnvironments


def make_grid():
    return GridWorldEnv(batch_size=8, max_steps=30)


class _GridWithGlobalNoise(GridWorldEnv):
    """A gridworld whose rewards carry noise from numpy's and Python's global
    generators, as many user environments draw theirs."""

    def _step(self, tensordict):
        out = super()._step(tensordict)
        noise = np.random.standard_normal(out["reward"].shape) + random.random()
        out["reward"] = out["reward"] + 0.01 * torch.as_tensor(noise, dtype=torch.float32)
        return out


def _grid_with_global_noise():
    return _GridWithGlobalNoise(batch_size=8, max_steps=30)


class NumberedGrids(GridWorldEnv):
    """Eight gridworlds, each observing its own number."""

    def __init__(self):
        super().__init__(batch_size=8, max_steps=30)
        self.observation_spec["grid"] = Categorical(8, shape=self.batch_size)

    def _reset(self, tensordict=None, **kwargs):
        return super()._reset(tensordict, **kwargs).set("grid", torch.arange(8))

    def _step(self, tensordict):
        return super()._step(tensordict).set("grid", torch.arange(8))


def _grid_noting_its_frozen_heap(folder: Path):
    """make_grid, after writing how many objects this process has frozen to a file
    named after it."""
    folder.mkdir(exist_ok=True)
    (folder / str(os.getpid())).write_text(str(gc.get_freeze_count()))
    return make_grid()


class _GridThatCrashes(GridWorldEnv):
    """A grid world whose process crashes at its first step, as a simulator's native
    code may (a segmentation fault)."""

    def _step(self, tensordict):
        os.kill(os.getpid(), signal.SIGSEGV)


def _grid_that_crashes():
    return _GridThatCrashes(batch_size=8, max_steps=30)


class _GridWithABug(GridWorldEnv):
    def _step(self, tensordict):
        raise ValueError("a bug in the environment")


def _grid_with_a_bug():
    return _GridWithABug(batch_size=8, max_steps=30)


def _first_worker(collection) -> int:
    """The pid of the collection's first worker (a process, or a Ray actor's)."""
    workers = collection.workers.pool
    if collection.settings.ray:
        import ray

        actor = workers.remote_collectors[0]
        return ray.get(actor.__ray_call__.remote(lambda self: os.getpid()))
    return workers.procs[0].pid


def _kill_a_worker(collection) -> None:
    """Kills the collection's first worker as the kernel's OOM killer would, and waits
    until it is gone."""
    pid = _first_worker(collection)
    os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while not _exited(pid) and time.monotonic() < deadline:
        time.sleep(0.05)


def _two_workers(tmp_path, module):
    """A collection over two worker processes of the gridworld, in segments."""
    cfg = _cfg(tmp_path, workers=2, batch_mode="segments", segment_length=5)
    env = make_grid()
    actor = mlp_actor(env, hidden=(16,), activation=nn.ReLU)
    return module.Collection(cfg, env, make_grid, actor, seed=cfg.seed, updates=0)


def _exited(pid: int) -> bool:
    try:  # a zombie until its parent reaps it: it runs no more
        return "zombie" in Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return True


def make_grid_models(env):
    kwargs = {"hidden": (32,), "activation": nn.ReLU}
    return mlp_actor(env, **kwargs), mlp_critic(env, **kwargs)


def _cfg(tmp_path, **overrides) -> TrainConfig:
    defaults = {
        "run_dir": tmp_path / "run",
        "total_frames": 100_000,
        "total_updates": 6,
        "episodes_per_batch": 8,
        "gamma": 1.0,
        "lr": 0.02,
        "eval_interval": 500,
        "eval_episodes": 1,
        "checkpoint_interval": 2,
        "progress": False,
    }
    return TrainConfig(**{**defaults, **overrides})


def _train(cfg, **kwargs):
    return train(cfg, recipe="grid", make_env=make_grid, make_models=make_grid_models, **kwargs)


def _cfg_unscaled_value(cfg, actor, critic, batch) -> float:
    """The critic's loss on ``batch``'s own rewards."""
    loss = make_loss(cfg, *copy.deepcopy((actor, critic)))
    with torch.no_grad():
        return loss(batch)["loss_value"].item()


def _logged(run_dir: Path, name: str) -> list[float]:
    """The values of scalar ``name`` in the order the run logged them."""
    rows = (run_dir / "logs" / "csv" / "scalars" / f"{name}.csv").read_text().split()
    return [float(row.split(",")[1]) for row in rows]


class TestTrain:
    def test_run_directory(self, tmp_path):
        summary = _train(_cfg(tmp_path))
        run = tmp_path / "run"
        assert json.loads((run / "summary.json").read_text()) == summary
        for key in ("recipe", "seed", "frames", "train_wall_s", "eval_mean_return"):
            assert key in summary
        assert summary["updates"] == 6 and summary["frames"] > 0
        assert (run / "checkpoint.pt").is_file() and (run / "learning_curve.png").is_file()
        scalars = run / "logs" / "csv" / "scalars"
        namespaces = {p.parent.name for p in scalars.glob("*/*.csv")}
        assert namespaces == {"train", "eval", "loss", "time"}

    def test_tensorboard_logs(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2, tensorboard=True))
        assert list((tmp_path / "run" / "logs" / "tensorboard").rglob("events.out.tfevents.*"))

    @pytest.mark.skipif(
        not all(importlib.util.find_spec(m) for m in ("tensorboard", "wandb", "mlflow")),
        reason="rl_pg[tensorboard,wandb,mlflow] is not installed",
    )
    def test_every_logger_at_once_gets_metrics_and_hyperparameters(self, tmp_path):
        import mlflow

        uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
        cfg = _cfg(tmp_path, total_updates=2, lr=0.0125, tensorboard=True, wandb=True)
        summary = _train(replace(cfg, mlflow=True, mlflow_uri=uri))
        run = tmp_path / "run"
        assert read_curve(run, "eval/mean_return")[1][-1] == summary["eval_mean_return"]
        (hparams,) = (run / "logs" / "csv" / "texts").glob("hparams*.txt")
        assert "lr: 0.0125" in hparams.read_text()
        assert list((run / "logs" / "tensorboard").rglob("events.out.tfevents.*"))
        (record,) = (run / "wandb").glob("offline-run-*/run-*.wandb")  # W&B's offline run
        data = record.read_bytes()
        assert b"eval/mean_return" in data and b"episodes_per_batch" in data
        client = mlflow.tracking.MlflowClient(uri)
        (logged,) = client.search_runs([client.get_experiment_by_name("grid").experiment_id])
        assert logged.data.params["lr"] == "0.0125"
        assert logged.data.tags["mlflow.runName"] == "run"
        assert logged.data.metrics["eval/mean_return"] == summary["eval_mean_return"]
        assert mlflow.active_run() is None  # ended with the run
        # held back and sent in batches, every update's metrics reach the store
        frames, values = read_curve(run, "loss/actor")
        history = client.get_metric_history(logged.info.run_id, "loss/actor")
        assert [m.step for m in history] == list(frames)
        assert [m.value for m in history] == pytest.approx(list(values))
        assert len(history) == summary["updates"] == 2

    def test_a_slow_viewer_backend_gets_fewer_points_and_never_slows_the_run_much(self, tmp_path):
        from torchrl.record.loggers import Logger

        from rl_pg.training.loggers import VIEWER_SHARE, Loggers

        class Slow(Logger):  # a backend whose every call costs as much as an update
            def __init__(self):
                self.steps, self.seconds = [], 0.0

            def _create_experiment(self):
                return None

            def log_metrics(self, metrics, step=None):
                start = time.perf_counter()
                time.sleep(0.002)
                self.steps.append(step)
                self.seconds += time.perf_counter() - start

            def log_scalar(self, name, value, step=None):
                self.steps.append(step)

            def log_hparams(self, cfg):
                pass

            def log_video(self, *args, **kwargs):
                pass

            def log_histogram(self, *args, **kwargs):
                pass

            def __repr__(self):
                return "Slow()"

        loggers = Loggers(_cfg(tmp_path), tmp_path, "grid", hparams={}, resume_at=None)
        slow = Slow()
        loggers.loggers.append(slow)
        start = time.perf_counter()
        for number in range(200):  # updates of 2 ms each
            time.sleep(0.002)
            loggers.log_metrics({"loss/actor": float(number)}, step=number)
        elapsed = time.perf_counter() - start
        loggers.close()
        # the CSV logs every update; the slow backend about one in twenty, spread over
        # the whole run, its time within its share (one call may overshoot it)
        assert list(read_curve(tmp_path, "loss/actor")[0]) == list(range(200))
        assert 3 <= len(slow.steps) < 100 and slow.steps[-1] >= 100, slow.steps
        assert slow.seconds <= VIEWER_SHARE * elapsed + slow.seconds / len(slow.steps)

    def test_a_missing_logger_package_names_its_extra(self, tmp_path, monkeypatch):
        hide_module(monkeypatch, "wandb")
        with pytest.raises(ImportError, match=r'--wandb needs the wandb extra: .*"rl_pg\[wandb\]"'):
            _train(_cfg(tmp_path, wandb=True))
        assert not (tmp_path / "run").exists()

    def test_solves_the_gridworld(self, tmp_path):
        threshold = GridWorldEnv().optimal_return - 1e-6
        cfg = _cfg(tmp_path, total_updates=60, eval_interval=1, threshold=threshold)
        summary = _train(cfg)
        assert summary["solved_at_frames"] is not None
        assert summary["eval_mean_return"] >= threshold

    def test_segments_mode(self, tmp_path):
        summary = _train(_cfg(tmp_path, batch_mode="segments", segment_length=10))
        assert summary["frames"] == 6 * 10 * 8

    def test_critic_steps_fit_the_baseline_and_leave_the_policy_to_one_step(self, tmp_path):
        summaries, weights = {}, {}
        for steps in (1, 20):
            run = tmp_path / f"steps{steps}"
            summaries[steps] = _train(
                _cfg(tmp_path, run_dir=run, critic_steps=steps, total_updates=1)
            )
            weights[steps] = run_weights(run)
        actor = [key for key in weights[1] if key.startswith("actor_network")]
        critic = [key for key in weights[1] if key.startswith("critic_network")]
        assert actor and critic
        for key in actor:  # the policy's one step is the same
            assert torch.equal(weights[1][key], weights[20][key]), key
        assert any(not torch.equal(weights[1][key], weights[20][key]) for key in critic)
        fitted = tmp_path / "steps20" / "logs" / "csv" / "scalars" / "loss" / "value_fitted.csv"
        first = tmp_path / "steps20" / "logs" / "csv" / "scalars" / "loss" / "value.csv"
        before = float(first.read_text().split(",")[-1])
        after = float(fitted.read_text().split(",")[-1])
        assert after < 0.5 * before

    def test_late_segments_join_into_one_longer_segment(self, tmp_path):
        # From segments_late_start on, each update joins segments_late consecutive
        # segments collected with one policy: from frame 0, that is the update of one
        # segment that many times longer, to the last weight and frame.
        joined, longer = tmp_path / "joined", tmp_path / "longer"
        common = {"batch_mode": "segments", "total_updates": 4, "eval_interval": 10**9}
        late = {"segments_late": 3, "segments_late_start": 0.0}
        summaries = {
            "joined": _train(_cfg(tmp_path, run_dir=joined, segment_length=5, **late, **common)),
            "longer": _train(_cfg(tmp_path, run_dir=longer, segment_length=15, **common)),
        }
        assert summaries["joined"]["frames"] == summaries["longer"]["frames"] == 4 * 15 * 8
        assert summaries["joined"]["updates"] == 4
        a, b = run_weights(joined), run_weights(longer)
        assert a.keys() == b.keys()
        for key in a:
            torch.testing.assert_close(a[key], b[key], msg=key)
        # from half the budget on: 2 short updates, then joined ones
        _train(_cfg(tmp_path, run_dir=tmp_path / "late", segment_length=5, segments_late=3,
                    segments_late_start=0.5, batch_mode="segments", total_frames=400,
                    total_updates=None, eval_interval=10**9))  # fmt: skip
        frames = [int(row.split(",")[0]) for row in (
            tmp_path / "late" / "logs" / "csv" / "scalars" / "train" / "episode_return.csv"
        ).read_text().split()]  # fmt: skip
        # rows: updates that finished an episode; 40 frames an update up to 200 (half the
        # budget), 120 after (the last update passes the budget, as any batch may)
        steps = np.diff([0, *frames])
        assert frames[-3:] == [200, 320, 440] and all(step % 40 == 0 for step in steps), steps

    def test_gae_with_lambda_one_is_reward_to_go_minus_v(self, tmp_path):
        # On whole episodes (truncations bootstrapped from V by both), GAE(lambda=1) is
        # the Monte-Carlo reward-to-go minus V: the same update; a lambda below 1 is not.
        weights = {}
        for name, override in {
            "rtg": {"returns": "reward_to_go"},
            "gae1": {"returns": "gae", "gae_lambda": 1.0},
            "gae05": {"returns": "gae", "gae_lambda": 0.5},
        }.items():
            run = tmp_path / name
            _train(_cfg(tmp_path, run_dir=run, gamma=0.9, total_updates=1, **override))
            weights[name] = run_weights(run)
        actor = [key for key in weights["rtg"] if key.startswith("actor_network")]
        assert actor
        for key in actor:
            torch.testing.assert_close(weights["gae1"][key], weights["rtg"][key])
        assert any(not torch.allclose(weights["gae05"][k], weights["rtg"][k]) for k in actor)

    @pytest.mark.parametrize("fisher", ["exact", "kfac"])
    def test_natural_steps_move_the_policy_by_max_kl(self, tmp_path, fisher):
        summary = _train(
            _cfg(
                tmp_path,
                optimizer="natural",
                fisher=fisher,
                max_kl=0.005,
                total_updates=5,
                baseline="running_mean",
            )
        )
        assert summary["updates"] == 5
        kl, fraction = (
            _logged(tmp_path / "run", "train/kl"),
            _logged(tmp_path / "run", "train/step_fraction"),
        )
        assert len(kl) == 5 and all(0 <= k <= 1.5 * 0.005 for k in kl)
        assert all(f > 0 for f in fraction[:1])  # the first step at least is taken
        # The critic takes its own (Adam) steps: it was fitted to some returns.
        assert len(_logged(tmp_path / "run", "loss/value")) == 5

    def test_the_controllers_move_the_rate_and_the_entropy_coefficient(self, tmp_path):
        _train(_cfg(tmp_path, lr_control="kl", target_kl=1e-6, entropy_coeff=0.05,
                    entropy_target=2.0, total_updates=4))  # fmt: skip
        lr = _logged(tmp_path / "run", "train/lr")
        assert lr[0] == 0.02 and lr[-1] < lr[0]  # every update moved far more than 1e-6
        # Updates far below the target raise the rate, to its bound (factors of lr).
        capped = tmp_path / "capped"
        _train(_cfg(tmp_path, run_dir=capped, lr_control="kl", target_kl=10.0,
                    kl_lr_range=(0.5, 2.0), total_updates=4, log_interval=1))  # fmt: skip
        assert _logged(capped, "train/lr") == pytest.approx([0.02, 0.03, 0.04, 0.04])
        assert len(_logged(tmp_path / "run", "train/kl")) == 4
        coeff = _logged(tmp_path / "run", "train/entropy_coeff")
        assert coeff[0] == 0.05 and coeff[-1] > coeff[0]  # entropy below 2 nats: up
        # Far above a target of 0 nats, with a negative floor: a penalty, held there.
        held = tmp_path / "held"
        _train(_cfg(tmp_path, run_dir=held, entropy_coeff=0.01, entropy_target=0.0,
                    entropy_target_lr=0.1, entropy_coeff_min=-0.02, total_updates=3))  # fmt: skip
        assert _logged(held, "train/entropy_coeff")[-1] == -0.02

    def test_group_baselines_train_on_groups_and_count_their_greedy_episodes(self, tmp_path):
        seen = []

        class Groups(Callback):
            def on_batch(self, run, batch):
                seen.append((batch["group"].unique().numel(), int(batch["greedy"].sum()),
                             int(batch["next", "done"].sum())))  # fmt: skip

        summary = _train(
            _cfg(tmp_path, baseline="greedy", group_size=3, total_updates=3), callbacks=[Groups()]
        )
        assert [(groups, episodes) for groups, _, episodes in seen] == [(2, 8)] * 3
        assert all(steps > 0 for _, steps, _ in seen)  # the greedy episodes' steps
        assert summary["frames"] >= sum(steps for _, steps, _ in seen)

    def test_adam_beta1_sets_the_average_of_the_gradients(self, tmp_path):
        # Adam's first step is the sign of the gradient whatever beta1 (bias correction);
        # from the second on, beta1 weighs the earlier gradients: the runs part there.
        weights, betas = {}, {}
        for beta1 in (0.9, 0.99):
            run = tmp_path / f"beta{beta1}"
            for updates in (1, 3):
                _train(
                    _cfg(
                        tmp_path,
                        run_dir=run / str(updates),
                        total_updates=updates,
                        adam_beta1=beta1,
                    )
                )
                weights[beta1, updates] = run_weights(run / str(updates))
            saved = load_checkpoint(run / "3" / "checkpoint.pt")
            betas[beta1] = {tuple(g["betas"]) for g in saved["optimizer"]["param_groups"]}
        assert betas == {0.9: {(0.9, 0.999)}, 0.99: {(0.99, 0.999)}}
        for key in weights[0.9, 1]:
            torch.testing.assert_close(weights[0.99, 1][key], weights[0.9, 1][key])
        assert any(
            not torch.allclose(weights[0.99, 3][k], weights[0.9, 3][k]) for k in weights[0.9, 3]
        )

    def test_linear_learning_rate_schedule(self, tmp_path):
        # 6 updates x 80 frames = total_frames: update k (0-based) starts at 80k frames.
        cfg = _cfg(
            tmp_path, batch_mode="segments", segment_length=10, total_frames=480, total_updates=None
        )
        summary = _train(replace(cfg, lr_schedule="linear"))
        assert summary["frames"] == 480
        assert _logged(tmp_path / "run", "train/lr") == pytest.approx(
            [0.02 * (1 - k / 6) for k in range(6)]
        )
        constant = _train(replace(cfg, run_dir=tmp_path / "constant"))
        assert _logged(tmp_path / "constant", "train/lr") == [0.02] * 6
        # Held at lr for the first half of total_frames (3 updates), then decayed over
        # the other 3 towards 0 at total_frames.
        _train(replace(cfg, run_dir=tmp_path / "held", lr_schedule="linear", lr_schedule_start=0.5))
        assert _logged(tmp_path / "held", "train/lr") == pytest.approx(
            [0.02] * 3 + [0.02 * (1 - k / 3) for k in range(3)]
        )
        assert constant["eval_mean_return"] is not None

    @pytest.mark.parametrize(
        ("end", "start"),
        [(0.0, 0.0), (-0.1, 0.0), (-0.1, 0.5)],
        ids=["to_zero", "into_a_penalty", "held_for_half_the_run"],
    )
    def test_linear_entropy_schedule(self, tmp_path, end, start):
        # From entropy_coeff to entropy_coeff_end; below 0 the bonus falls through 0
        # into a penalty. With a start, it holds at entropy_coeff for that fraction of
        # total_frames first (here the first 3 of 6 updates), then moves over the rest.
        cfg = _cfg(
            tmp_path,
            batch_mode="segments",
            segment_length=10,
            total_frames=480,
            total_updates=None,
            entropy_coeff=0.05,
            entropy_schedule="linear",
            entropy_coeff_end=end,
            entropy_schedule_start=start,
        )
        _train(cfg)
        run = tmp_path / "run"
        coeff = _logged(run, "train/entropy_coeff")
        held = round(6 * start)
        expected = [0.05] * held + [0.05 + (end - 0.05) * k / (6 - held) for k in range(6 - held)]
        assert coeff == pytest.approx(expected)
        # The entropy term the update minimised is the scheduled bonus times the entropy
        # (with the penalty's sign where it is one).
        entropy = _logged(run, "train/entropy")
        expected = [-c * h for c, h in zip(coeff, entropy, strict=True)]
        assert _logged(run, "loss/entropy") == pytest.approx(expected, rel=1e-5)
        assert _logged(run, "train/lr") == [0.02] * 6  # its own, constant, schedule
        if end < 0:
            assert coeff[0] > 0 > coeff[-1]

    @pytest.mark.parametrize("returns", ["reward_to_go", "gae"])
    def test_reward_scale_is_seen_by_the_loss_only(self, tmp_path, returns):
        # One update with reward_scale=0.1 is the update on rewards multiplied by 0.1 (the
        # same losses, critic steps and parameters after); the batch the run counts its
        # episode returns from keeps the environment's rewards.
        env = make_grid()
        torch.manual_seed(0)
        actor, critic = make_grid_models(env)
        batch = env.rollout(20, actor, break_when_any_done=False)
        batch["next", "reward"] += torch.randn_like(batch["next", "reward"])
        rewards = batch["next", "reward"].clone()
        cfg = _cfg(tmp_path, returns=returns, critic_steps=3, max_grad_norm=0.5)
        results = []
        for scale, data in ((0.1, batch), (1.0, batch.clone())):
            if scale == 1.0:
                data["next", "reward"] = data["next", "reward"] * 0.1
            loss = make_loss(replace(cfg, reward_scale=scale), *copy.deepcopy((actor, critic)))
            optimizer = make_optimizer(cfg, loss)
            metrics = update(replace(cfg, reward_scale=scale), loss, optimizer, data, lr=cfg.lr)
            results.append((metrics, [p.detach().clone() for p in loss.parameters()]))
        (scaled, scaled_params), (by_hand, by_hand_params) = results
        assert scaled == pytest.approx(by_hand, rel=1e-6)
        assert scaled["loss/value"] != pytest.approx(_cfg_unscaled_value(cfg, actor, critic, batch))
        for a, b in zip(scaled_params, by_hand_params, strict=True):
            torch.testing.assert_close(a, b)
        assert torch.equal(batch["next", "reward"], rewards)

    def test_refuses_to_overwrite_a_run(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=1))
        before = (tmp_path / "run" / "checkpoint.pt").read_bytes()
        with pytest.raises(CheckpointError, match="already holds a checkpoint; pass --resume"):
            _train(_cfg(tmp_path, total_updates=1))
        assert (tmp_path / "run" / "checkpoint.pt").read_bytes() == before

    def test_a_checkpoint_restores_every_random_generator_from_plain_data(self, tmp_path):
        import random

        from rl_pg.training.checkpoints import restore_rng

        _train(_cfg(tmp_path, total_updates=1))
        saved = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
        assert isinstance(saved["rng"]["numpy"]["state"]["key"], torch.Tensor)  # no pickled array
        draws = []
        for scramble in (1, 2):  # the generators anywhere else before the restore
            np.random.seed(scramble), random.seed(scramble), torch.manual_seed(scramble)
            restore_rng(saved)
            draws.append((np.random.rand(3).tolist(), random.random(), torch.rand(2).tolist()))
        assert draws[0] == draws[1]

    def test_resume_without_checkpoint(self, tmp_path):
        with pytest.raises(CheckpointError, match="No checkpoint at"):
            _train(_cfg(tmp_path, resume=True))

    def test_resume_with_another_configuration(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2))
        with pytest.raises(CheckpointError, match=r"different configuration \(lr: 0.02 -> 0.5\)"):
            _train(_cfg(tmp_path, resume=True, lr=0.5))

    def test_a_run_from_before_a_new_field_resumes_as_that_fields_default(self, tmp_path):
        from rl_pg.checkpoint import save_checkpoint

        _train(_cfg(tmp_path, total_updates=2))
        path = tmp_path / "run" / "checkpoint.pt"
        saved = load_checkpoint(path)
        del saved["config"]["critic_steps"]  # as a version without the field wrote it
        save_checkpoint(saved, path)
        with pytest.raises(CheckpointError, match=r"\(critic_steps: 1 -> 3\)"):
            _train(_cfg(tmp_path, resume=True, total_updates=3, critic_steps=3))
        assert _train(_cfg(tmp_path, resume=True, total_updates=3))["updates"] == 3

    def test_a_run_resumes_on_the_evaluation_seeds_it_started_with(self, tmp_path, monkeypatch):
        from rl_pg.checkpoint import save_checkpoint
        from rl_pg.training import selection

        evaluating, seeds_set = [], []

        def evaluate_run(*args, **kwargs):  # records the seeds set while it runs
            evaluating.append(True)
            try:
                return real_evaluate_run(*args, **kwargs)
            finally:
                evaluating.pop()

        real_evaluate_run, real_set_seed = selection.evaluate_run, GridWorldEnv.set_seed

        def set_seed(self, seed=None, *args, **kwargs):
            if evaluating:
                seeds_set.append(seed)
            return real_set_seed(self, seed, *args, **kwargs)

        monkeypatch.setattr("rl_pg.training.run.evaluate_run", evaluate_run)
        monkeypatch.setattr(GridWorldEnv, "set_seed", set_seed)
        _train(_cfg(tmp_path, seed=1, total_updates=2, eval_interval=1))
        assert set(seeds_set) == {evaluation_seed(1)} != {1 + 1_000_003}
        path = tmp_path / "run" / "checkpoint.pt"
        saved = load_checkpoint(path)
        assert saved["state"]["streams"]["evaluation"] == evaluation_seed(1)
        del saved["state"]["streams"]  # as a version before the streams were kept wrote it
        save_checkpoint(saved, path)
        seeds_set.clear()
        _train(_cfg(tmp_path, seed=1, resume=True, total_updates=4, eval_interval=1))
        # the run's first evaluations chose its best.pt on these start states: it goes on
        assert set(seeds_set) == {1 + 1_000_003}
        resumed = load_checkpoint(path)["state"]["streams"]
        assert resumed == {"evaluation": 1 + 1_000_003, "confirmation": 1 + 3 * 1_000_003}

    def test_a_run_from_before_a_default_changed_resumes_as_it_ran(self, tmp_path):
        # A field whose default changed after it was added: a stored config without the
        # field ran at the old default, which `absent_means` records.
        from rl_pg.checkpoint import save_checkpoint

        @dataclass
        class Changed(TrainConfig, entropy_coeff=0.05):
            absent_means: ClassVar[dict[str, Any]] = {"entropy_coeff": 0.0}

        _train(_cfg(tmp_path, total_updates=2))  # entropy_coeff 0.0, the old default
        path = tmp_path / "run" / "checkpoint.pt"
        saved = load_checkpoint(path)
        del saved["config"]["entropy_coeff"]  # as a version without the field wrote it
        save_checkpoint(saved, path)
        stored = Changed.from_stored(saved["config"], resume=True, total_updates=3)
        assert (stored.entropy_coeff, Changed().entropy_coeff) == (0.0, 0.05)
        with pytest.raises(CheckpointError, match=r"\(entropy_coeff: 0.0 -> 0.05\)"):
            _train(replace(stored, entropy_coeff=0.05))
        assert _train(stored)["updates"] == 3

    def test_resume_from_another_recipe(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2))
        with pytest.raises(CheckpointError, match="written by recipe 'grid'"):
            train(
                _cfg(tmp_path, resume=True),
                recipe="other",
                make_env=make_grid,
                make_models=make_grid_models,
            )

    def test_resume_from_a_corrupted_checkpoint(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2))
        path = tmp_path / "run" / "checkpoint.pt"
        path.write_bytes(path.read_bytes()[:100])
        with pytest.raises(CheckpointError, match="is corrupted"):
            _train(_cfg(tmp_path, resume=True))
        assert len(path.read_bytes()) == 100  # left as it was

    def test_popart_critic_is_rebuilt_from_its_checkpoint(self, tmp_path):
        # Evaluation and play build the recipe's models and load a checkpoint: a critic
        # trained with --value-norm popart gets its PopArt layer back, statistics included.
        _train(_cfg(tmp_path, value_norm="popart", total_updates=3))
        saved = read_run(tmp_path / "run")
        env = make_grid()
        actor, critic = make_grid_models(env)
        load_models(saved, actor, critic)
        head = next(m for m in critic.modules() if isinstance(m, PopArt))
        assert head.updated and head.scale().item() != 1.0
        stored = {k.removeprefix("critic_network."): v for k, v in saved["loss"].items()}
        for key, value in critic.state_dict().items():
            assert torch.equal(value, stored[key]), key
        with pytest.raises(ValueError, match="--value-norm popart"):
            train(
                _cfg(tmp_path, run_dir=tmp_path / "nocritic", value_norm="popart"),
                recipe="grid",
                make_env=make_grid,
                make_models=lambda env: (make_grid_models(env)[0], None),
            )

    def test_resume_with_models_that_do_not_fit(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2))

        def wider(env):
            return mlp_actor(env, hidden=(64,)), mlp_critic(env, hidden=(64,))

        with pytest.raises(CheckpointError, match="does not fit the models"):
            train(_cfg(tmp_path, resume=True), recipe="grid", make_env=make_grid, make_models=wider)

    @pytest.mark.parametrize(
        "schedule",
        [
            {},
            {"lr_schedule": "linear", "total_frames": 1500},
            {"lr_schedule": "linear", "lr_schedule_start": 0.4, "total_frames": 1500},
            {"entropy_schedule": "linear", "entropy_coeff": 0.05, "total_frames": 1500},
            {
                "entropy_schedule": "linear",
                "entropy_coeff": 0.05,
                "entropy_coeff_end": -0.05,
                "total_frames": 1500,
            },
            {
                "entropy_schedule": "linear",
                "entropy_coeff": 0.05,
                "entropy_coeff_end": -0.05,
                "entropy_schedule_start": 0.4,
                "total_frames": 1500,
            },
            {"value_norm": "popart"},
            {"policy_ema": 0.9},
            {"confirm_episodes": 3, "eval_interval": 100},
            {
                "baseline": "leave_one_out",
                "optimizer": "natural",
                "fisher": "kfac",  # samples actions for its factors: the random stream resumes
                "entropy_coeff": 0.05,
                "entropy_target": 0.8,
            },
            {"baseline": "greedy", "group_size": 3, "group_scale": True, "lr_control": "kl"},
        ],
        ids=[
            "constant",
            "linear",
            "late_linear",
            "linear_entropy",
            "entropy_penalty",
            "late_entropy_penalty",
            "popart",
            "policy_ema",
            "confirm",
            "groups_natural_entropy_target",
            "greedy_groups_kl_lr",
        ],
    )
    def test_resume_continues_exactly(self, tmp_path, schedule):
        straight = _cfg(tmp_path, run_dir=tmp_path / "straight", total_updates=6, **schedule)
        _train(straight)
        split = _cfg(tmp_path, run_dir=tmp_path / "split", total_updates=4, **schedule)
        _train(split)
        resumed = _train(
            _cfg(tmp_path, run_dir=tmp_path / "split", total_updates=6, resume=True, **schedule)
        )
        assert_same_run(resumed, tmp_path / "split", tmp_path / "straight")

    def test_segment_results_do_not_depend_on_the_checkpoint_interval(self, tmp_path):
        summaries, weights = [], []
        for interval in (1, 3, 1000):
            run = tmp_path / f"every{interval}"
            cfg = _cfg(tmp_path, run_dir=run, total_updates=11, checkpoint_interval=interval)
            summaries.append(_train(replace(cfg, **SEGMENTS, log_interval=2)))
            weights.append(run_weights(run))
        for summary in summaries[1:]:
            for key in ("frames", "eval_mean_return", "best_eval_mean_return"):
                assert summary[key] == summaries[0][key]
        for other in weights[1:]:
            for key, value in weights[0].items():
                assert torch.equal(value, other[key]), key
        curves = [read_curve(tmp_path / f"every{i}", "train/episode_return") for i in (1, 1000)]
        assert np.array_equal(curves[0][1], curves[1][1])

    def test_resume_continues_the_global_generators_an_environment_draws_from(self, tmp_path):
        # numpy's and Python's generators go on from where the checkpoint left them, not
        # from the seed, nor from wherever this process had left them.
        noisy = {"make_env": _grid_with_global_noise}
        straight = _cfg(tmp_path, run_dir=tmp_path / "straight", total_updates=4)
        train(straight, recipe="grid", make_models=make_grid_models, **noisy)
        split = _cfg(tmp_path, run_dir=tmp_path / "split", total_updates=2)
        train(split, recipe="grid", make_models=make_grid_models, **noisy)
        np.random.seed(99), random.seed(99)
        resumed = train(
            replace(split, total_updates=4, resume=True), recipe="grid",
            make_models=make_grid_models, **noisy,
        )  # fmt: skip
        assert_same_run(resumed, tmp_path / "split", tmp_path / "straight")

    @pytest.mark.parametrize("split", [5, 6, 8])  # on, just after and between restarts
    def test_segment_resume_between_restarts_is_exact(self, tmp_path, split):
        common = {**SEGMENTS, "log_interval": 3, "checkpoint_interval": 1000}
        _train(_cfg(tmp_path, run_dir=tmp_path / "straight", total_updates=13, **common))
        _train(_cfg(tmp_path, run_dir=tmp_path / "split", total_updates=split, **common))
        resumed = _train(
            _cfg(tmp_path, run_dir=tmp_path / "split", total_updates=13, resume=True, **common)
        )
        assert_same_run(resumed, tmp_path / "split", tmp_path / "straight")
        straight, split_run = (
            read_curve(tmp_path / run, "train/episode_return") for run in ("straight", "split")
        )
        assert np.array_equal(straight[1], split_run[1])  # episodes in flight carried over

    def test_non_finite_gradient_stops_and_keeps_the_checkpoint(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2))
        path = tmp_path / "run" / "checkpoint.pt"
        before = path.read_bytes()
        with pytest.raises(TrainingDiverged, match="gradient norm became nan"):
            train(
                _cfg(tmp_path, resume=True, total_updates=4),
                recipe="grid",
                make_env=make_grid,
                make_models=_models_with_nan_gradient,
            )
        assert path.read_bytes() == before

    @pytest.mark.parametrize(
        "ray",
        [
            False,
            pytest.param(
                True,
                marks=pytest.mark.skipif(
                    importlib.util.find_spec("ray") is None, reason="ray is not installed"
                ),
            ),
        ],
    )
    def test_workers_freeze_their_imports_get_new_weights_and_are_replaced_when_lost(
        self, tmp_path, ray, capfd, monkeypatch, request
    ):
        from rl_pg.training import workers as workers_module
        from rl_pg.training.collection import Collection

        if ray:
            request.getfixturevalue("local_ray")

        # Two worker processes; one Ray actor (each costs an import of torch and rl_pg;
        # the two-node test runs two).
        n = 1 if ray else 2
        cfg = _cfg(tmp_path, workers=n, ray=ray, batch_mode="segments", segment_length=5)
        env = make_grid()
        actor = mlp_actor(env, hidden=(16,), activation=nn.ReLU, normalize=True)
        user_path = os.environ.get("PYTHONPATH")
        frozen_here, heaps = gc.get_freeze_count(), tmp_path / "heaps"
        make_env = partial(_grid_noting_its_frozen_heap, heaps)
        collection = Collection(cfg, env, make_env, actor, seed=cfg.seed, updates=0)
        # Ray's local instance got this process's sys.path (the actors import make_grid
        # from this file), and this process's environment is left as it was.
        assert os.environ.get("PYTHONPATH") == user_path
        try:
            batches = iter(collection)
            update_running_norms(actor, next(batches))  # as the training loop does
            assert next(m for m in actor.modules() if isinstance(m, RunningNorm)).stats.count > 0
            last = [m for m in actor.modules() if isinstance(m, nn.Linear)][-1]
            with torch.no_grad():  # a policy that mostly moves right (action 2)
                for parameter in actor.parameters():
                    parameter.mul_(0.1)
                last.bias[2] = 50.0
            collection.after_update(1)
            next(batches)  # at most one batch in flight may predate the new weights
            batch = next(batches)
            # A worker lost mid-run is replaced: new workers collect the batch again,
            # with the learner's weights (the checks below read this batch). A worker
            # process is killed (as by the OOM killer), twice; a Ray actor hangs
            # (stopped), and is ended through Ray past the time limit, which its replacing
            # then sees as a killed actor (a Ray replacement costs about 10 s).
            if ray:
                monkeypatch.setattr(workers_module, "STALL_LIMIT_S", 5.0)
                os.kill(_first_worker(collection), signal.SIGSTOP)
                batch = next(batches)
            else:  # and between an update and the next
                _kill_a_worker(collection)
                batch = next(batches)
                _kill_a_worker(collection)
                collection.after_update(2)
                batch = next(batches)
        finally:
            collection.shutdown()
        err = capfd.readouterr().err
        lost = err.count("rl-pg: collection lost a worker")
        assert lost == (1 if ray else 2), err
        if ray:
            assert "sent no batch in 5 s, so rl-pg ended it" in err, err
        # Each worker froze its imports (torch, TorchRL, ...) before building its grid;
        # this process, which reads the specs from the factory too, froze nothing new
        # (frozen objects may die).
        counts = {int(path.name): int(path.read_text()) for path in heaps.iterdir()}
        workers = [count for pid, count in counts.items() if pid != os.getpid()]
        assert len(workers) == n * (1 + lost) and min(workers) > 100_000, counts
        assert gc.get_freeze_count() <= frozen_here
        actions = batch["action"]
        if actions.shape[-1] == 4:  # one-hot
            actions = actions.argmax(-1)
        assert (actions == 2).all()
        # The workers acted with the learner's weights and statistics: their logits are
        # the learner's.
        with torch.no_grad():
            recomputed = actor(batch.exclude("logits", "action").clone())["logits"]
        torch.testing.assert_close(recomputed, batch["logits"])

    def test_ray_workers_that_cannot_join_the_weight_sync_say_why(
        self, tmp_path, monkeypatch, local_ray
    ):
        from datetime import timedelta

        import torchrl.weight_update._ray as weight_sync

        from rl_pg.training.collection import Collection

        # As a firewall between the nodes, or a machine too busy to start the workers:
        # TorchRL's time for them to join its gloo group runs out.
        monkeypatch.setattr(weight_sync, "_DIST_TIMEOUT", timedelta(milliseconds=1))
        cfg = _cfg(tmp_path, workers=1, ray=True, batch_mode="segments", segment_length=5)
        env = make_grid()
        actor = mlp_actor(env, hidden=(16,), activation=nn.ReLU)
        cpus = local_ray.available_resources()["CPU"]
        with pytest.raises(RuntimeError, match="did not join the trainer's weight-sync"):
            Collection(cfg, env, make_grid, actor, seed=cfg.seed, updates=0)
        # and its actors are gone, their CPUs free (on a cluster, for the next run)
        deadline = time.monotonic() + 30
        while local_ray.available_resources().get("CPU") != cpus:
            assert time.monotonic() < deadline, local_ray.available_resources()
            time.sleep(0.1)

    def test_a_worker_lost_again_and_again_stops_the_run_naming_it(
        self, tmp_path, capfd, monkeypatch
    ):
        from rl_pg.training import collection as module
        from rl_pg.training import workers as workers_module

        monkeypatch.setattr(workers_module, "REPLACEMENTS", 1)  # each costs two new processes
        cfg = _cfg(tmp_path, workers=2, batch_mode="segments", segment_length=5)
        env = make_grid()
        actor = mlp_actor(env, hidden=(16,), activation=nn.ReLU)
        collection = module.Collection(
            cfg, env, _grid_that_crashes, actor, seed=cfg.seed, updates=0
        )
        try:
            with pytest.raises(RuntimeError) as raised:
                next(iter(collection))
        finally:
            collection.shutdown()
        message = str(raised.value)
        assert "lost a worker 2 times in a row, the last time: worker process" in message
        assert "killed by SIGSEGV" in message and "rl-pg resume" in message, message
        assert capfd.readouterr().err.count("New workers take over") == 1
        # An exception in the environment is a bug new workers would meet again: it
        # stops the run at once (the worker prints its traceback: to the stderr of the
        # fork server, which predates capfd here), nothing replaced.
        collection = module.Collection(cfg, env, _grid_with_a_bug, actor, seed=cfg.seed, updates=0)
        try:
            with pytest.raises(RuntimeError, match="exit code 1"):
                next(iter(collection))
        finally:
            collection.shutdown()
        assert "New workers" not in capfd.readouterr().err

    def test_workers_gone_with_their_killed_fork_server_are_replaced(self, tmp_path, capfd):
        from multiprocessing import forkserver

        from rl_pg.training import collection as module

        collection = _two_workers(tmp_path, module)
        try:
            batches = iter(collection)
            next(batches)
            # as `pkill -9 -f multiprocessing.forkserver` would: the server and its workers
            server = forkserver._forkserver._forkserver_pid
            for pid in (server, *(proc.pid for proc in collection.workers.pool.procs)):
                os.kill(pid, signal.SIGKILL)
            batch = next(batches)  # new workers, from a new fork server
        finally:
            collection.shutdown()
        err = capfd.readouterr().err
        assert err.count("is gone with the fork server that started it (killed)") == 2, err
        assert "New workers take over" in err and batch.numel() > 0

    def test_a_hung_worker_is_ended_and_replaced_within_the_stated_time(
        self, tmp_path, capfd, monkeypatch
    ):
        from rl_pg.training import collection as module
        from rl_pg.training import workers as workers_module

        # As a worker stopped by a signal, deadlocked or stuck in its simulator: it sends
        # nothing. Past the limit, the workers are ended and new ones take over.
        monkeypatch.setattr(workers_module, "STALL_LIMIT_S", 2.0)
        collection = _two_workers(tmp_path, module)
        try:
            batches = iter(collection)
            next(batches)
            next(batches)
            stopped = collection.workers.pool.procs[1].pid
            os.kill(stopped, signal.SIGSTOP)
            start = time.monotonic()
            batch = next(batches)  # from the new workers
            waited = time.monotonic() - start
        finally:
            collection.shutdown()
        err = capfd.readouterr().err
        assert f"(pid {stopped}) sent no batch in 2 s (stopped), so rl-pg ended it" in err, err
        assert "New workers take over" in err and batch.numel() > 0
        assert 2.0 <= waited < 60  # the limit, then the new workers' start

    @pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed")
    def test_a_lost_ray_actor_is_named_with_where_it_ran_and_why(self):
        from ray.core.generated.common_pb2 import ActorDiedErrorContext
        from ray.exceptions import ActorDiedError

        from rl_pg.training.workers import _actor_lost

        # Ray's error for an actor whose process was killed (as by the OOM killer)
        killed = ActorDiedError(ActorDiedErrorContext(
            class_name="Collector", actor_id=bytes(16), pid=28803, node_ip_address="10.0.0.7",
            error_message="The actor is dead because its worker process has died. Worker "
            "exit type: SYSTEM_ERROR Worker exit detail: Worker unexpectedly exits with a "
            "connection error code 2. End of file. Some common causes include: (1) ...",
        ))  # fmt: skip
        assert _actor_lost(killed) == (
            "Ray actor Collector (pid 28803 on 10.0.0.7): Worker unexpectedly exits with a "
            "connection error code 2"
        )
        ended = "sent no batch in 300 s, so rl-pg ended it"  # rl-pg's own reason prevails
        assert _actor_lost(killed, ended).endswith(f"(pid 28803 on 10.0.0.7): {ended}")
        unknown = ActorDiedError()  # no cause known
        assert _actor_lost(unknown) == (
            "Ray actor: The actor died unexpectedly before finishing this task"
        )

    @pytest.mark.parametrize("workers", [1, 2])
    def test_whole_episode_batches_are_new_episodes_of_each_environment(self, tmp_path, workers):
        # Every batch holds exactly the episodes asked for, each environment's share
        # fixed in advance: 8 episodes from 8 grids (per worker) are one from each grid
        # (of the first worker), whatever their lengths. The first episodes to end would
        # take two from a grid whose episodes are short and none from a slow one.
        class Batches(Callback):
            def __init__(self):
                self.grids, self.lengths = [], []

            def on_batch(self, run, batch):
                done = batch["next", "done"].squeeze(-1)
                self.grids.append(batch["grid"][done].tolist())
                self.lengths.append(batch.numel())

        seen = Batches()
        cfg = _cfg(tmp_path, workers=workers, total_updates=4)
        summary = train(cfg, recipe="grid", make_env=NumberedGrids, make_models=make_grid_models,
                        callbacks=[seen])  # fmt: skip
        assert summary["updates"] == 4 and seen.grids == [list(range(8))] * 4
        assert summary["frames"] >= sum(seen.lengths)

    @pytest.mark.parametrize(
        ("override", "message"),
        [
            ({"batch_mode": "steps"}, r"batch_mode \(--batch-mode\) must be one of"),
            ({"lr_schedule": "cosine"}, "lr_schedule .* must be one of"),
            ({"episodes_per_batch": 0}, "episodes_per_batch .* must be an integer >= 1"),
            ({"gamma": 1.5}, r"gamma \(--gamma\) must be a finite number >= 0 and <= 1"),
            ({"lr": 0.0}, r"lr \(--lr\) must be a finite number > 0"),
            ({"lr": float("nan")}, r"lr \(--lr\) must be a finite number > 0"),
            ({"max_grad_norm": -1.0}, r"max_grad_norm \(--max-grad-norm\) .* > 0, got -1"),
            ({"weight_decay": -0.1}, "weight_decay .* >= 0"),
            ({"entropy_coeff": float("inf")}, "entropy_coeff .* finite number >= 0"),
            ({"threshold": float("nan")}, "threshold .* must be a finite number"),
            ({"threads": 0}, r"threads \(--threads\) must be an integer >= 1"),
            ({"seed": -1}, r"seed \(--seed\) must be an integer >= 0"),
            ({"total_updates": 0}, "total_updates .* must be an integer >= 1"),
            ({"ray": True}, "use --batch-mode segments with --ray"),
            ({"critic_steps": 0}, r"critic_steps \(--critic-steps\) must be an integer >= 1"),
            ({"critic_steps": 5, "baseline": "ema"}, "--critic-steps 5 fits a critic, but"),
            ({"segments_late": 2}, "--segments-late 2 joins segments .* use --batch-mode seg"),
            ({"segments_late": 0}, r"segments_late \(--segments-late\) must be an integer >= 1"),
            ({"segments_late_start": 1.0}, "segments_late_start .* must be"),
            ({"returns": "gae", "baseline": "running_mean"}, "--returns gae estimates"),
            ({"gae_lambda": 1.5}, r"gae_lambda \(--gae-lambda\) must be a finite number"),
            ({"resume": True, "run_dir": None}, "--resume needs --run-dir"),
            ({"entropy_coeff": 0.01, "entropy_coeff_end": -0.1}, "add --entropy-schedule linear"),
            (
                {"entropy_schedule": "linear", "entropy_coeff_end": -0.1},
                "a positive --entropy-coeff",
            ),
            ({"entropy_coeff_end": float("nan")}, "entropy_coeff_end .* finite number"),
            ({"entropy_schedule_start": 0.5}, "starts moving: add --entropy-schedule linear"),
            ({"lr_schedule_start": 0.5}, "starts decaying: add --lr-schedule linear"),
            ({"optimizer": "sgd", "adam_beta1": 0.99}, "use --optimizer adam"),
            ({"adam_beta1": 1.0}, "adam_beta1 .* must be"),
            ({"lr_schedule": "linear", "lr_schedule_start": 1.0}, "lr_schedule_start .* must be"),
            (
                {"entropy_schedule": "linear", "entropy_schedule_start": 1.0},
                "entropy_schedule_start .* must be",
            ),
            ({"baseline": "leave_one_out", "batch_mode": "segments"},
             "--baseline leave_one_out plays episodes in groups .* --batch-mode episodes"),
            ({"baseline": "group_mean", "workers": 2}, "with one local collector"),
            ({"baseline": "greedy", "group_size": 4}, "groups of 5 episodes .* multiple of 5"),
            ({"baseline": "leave_one_out", "group_size": 1}, r"group_size \(--group-size\)"),
            ({"group_scale": True}, "--group-scale divides group advantages"),
            ({"lr_control": "kl", "optimizer": "natural"}, "--lr-control kl sets the learning"),
            ({"fisher": "kfac"}, "--fisher kfac sets how the natural-gradient step"),
            ({"lr_control": "kl", "lr_schedule": "linear"}, "use one"),
            ({"kl_lr_range": (2.0, 10.0)}, r"LOW must be in \(0, 1\] and HIGH finite"),
            ({"kl_lr_range": (0.0, 10.0)}, r"--kl-lr-range 0.0 10.0 bounds the rate"),
            ({"entropy_target": 0.5}, "--entropy-target 0.5 learns the entropy coefficient"),
            ({"entropy_coeff_min": -0.1}, "--entropy-coeff-min -0.1 bounds the learned"),
            ({"max_kl": 0.0}, r"max_kl \(--max-kl\) must be a finite number > 0"),
        ],
    )  # fmt: skip
    def test_bad_configuration(self, tmp_path, override, message):
        with pytest.raises(ValueError, match=message):
            _cfg(tmp_path, **override)

    def test_groups_need_whole_rounds_of_the_recipes_environments(self, tmp_path):
        # Grouped batches play rounds of one episode per environment: the episodes a
        # multiple of the environments, and the greedy ones at fixed places.
        @dataclass
        class Config(TrainConfig, BatchedEnvironments, num_envs=16):
            pass

        with pytest.raises(ValueError, match=r"a multiple of --num-envs .* 8 and 16"):
            Config(baseline="leave_one_out", episodes_per_batch=8)
        assert Config(baseline="leave_one_out", episodes_per_batch=32).num_envs == 16
        assert Config(baseline="leave_one_out", num_envs=1, episodes_per_batch=8).num_envs == 1
        with pytest.raises(ValueError, match="set --num-envs to a multiple of 5"):
            Config(baseline="greedy", num_envs=4, episodes_per_batch=20)

    def test_a_config_that_declares_what_a_check_reads_must_say_so_by_its_bases(self):
        # A field of its own named num_envs would be no field the checks read: the
        # group-baseline and --overlap checks would pass it by unseen.
        for name, mixin in (("num_envs", "BatchedEnvironments"), ("backend", "EnvPoolBackend")):
            with pytest.raises(TypeError, match=rf"declares {name}.*{mixin}: add that class"):
                make_dataclass("Config", [(name, int, 16)], bases=(TrainConfig,))

    def test_a_config_changed_after_it_was_made_is_checked_again(self, tmp_path):
        cfg = _cfg(tmp_path)
        cfg.max_grad_norm = -1.0  # would turn every update into gradient ascent
        with pytest.raises(ValueError, match=r"max_grad_norm .* > 0"):
            _train(cfg)
        assert not (tmp_path / "run").exists()

    @pytest.mark.parametrize(
        ("override", "match"),
        [({"eval_greedy": "yes"}, "must be True or False"), ({"total_frames": 1e5}, "integer")],
    )
    def test_values_of_the_wrong_kind(self, tmp_path, override, match):
        with pytest.raises(TypeError, match=match):
            _cfg(tmp_path, **override)

    def test_numpy_numbers_are_accepted(self, tmp_path):
        cfg = _cfg(tmp_path, lr=np.float32(0.02), gamma=np.float64(1.0), total_updates=np.int64(2))
        assert (type(cfg.lr), type(cfg.gamma), type(cfg.total_updates)) == (float, float, int)


class _NanGradient(nn.Module):
    """Adds sqrt(0 * x): nothing to the value, NaN (= sqrt'(0) * 0) to its gradient."""

    def forward(self, value):
        return value + torch.sqrt(torch.zeros_like(value) * value)


def _models_with_nan_gradient(env):
    actor, critic = make_grid_models(env)
    # Appended after the critic's layers, so the checkpoint's parameter names still fit.
    layers = nn.Sequential(*critic.module, _NanGradient())
    return actor, ValueOperator(layers, in_keys=["observation"])


_KILLABLE_RUN = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    from test_loop import _cfg, _train
    from pathlib import Path
    _train(_cfg(Path({tmp!r}), run_dir=Path({run!r}), total_updates=12, checkpoint_interval=1,
                **{extra!r}))
    """
)
SEGMENTS = {"batch_mode": "segments", "segment_length": 10, "env_restart_interval": 5}


def _signal_when_ready(processes, ready, send, *, timeout: float = 120.0) -> None:
    """Polls ``ready(name)`` for every process of ``{name: Popen}`` and calls
    ``send(name, process)`` as soon as it holds; fails if a process ends first or the
    timeout passes."""
    waiting = dict(processes)
    deadline = time.monotonic() + timeout
    while waiting:
        for name, process in list(waiting.items()):
            if ready(name):
                send(name, process)
                del waiting[name]
            else:
                assert process.poll() is None, f"{name} ended first: {process.communicate()}"
                assert time.monotonic() < deadline, f"{name}: not ready after {timeout} s"
        time.sleep(0.02)


def _updates_saved(run: Path) -> int:
    checkpoint = run / "checkpoint.pt"
    return load_checkpoint(checkpoint)["state"]["updates"] if checkpoint.is_file() else 0


def _lines(path: Path) -> int:
    return path.read_text().count("\n") if path.is_file() else 0


class TestKilledRun:
    def test_sigkill_then_resume_ends_like_an_uninterrupted_run(self, tmp_path):
        # Whole-episode and segment batches, each killed in a process of its own; the
        # two run side by side (most of their time is imports).
        modes = {"episodes": {}, "segments": SEGMENTS}
        processes = {}
        for mode, extra in modes.items():
            script = _KILLABLE_RUN.format(
                tests=str(Path(__file__).parent), tmp=str(tmp_path / mode),
                run=str(tmp_path / mode / "killed"), extra=extra,
            )  # fmt: skip
            processes[mode] = subprocess.Popen(
                [sys.executable, "-c", script], env=os.environ.copy()
            )
        try:
            _signal_when_ready(
                processes,
                lambda mode: _updates_saved(tmp_path / mode / "killed") >= 4,
                lambda _, process: process.send_signal(signal.SIGKILL),
            )
        finally:
            for process in processes.values():
                process.kill()
                process.wait()
        for mode, extra in modes.items():
            # The uninterrupted run checkpoints every 2 updates, the killed one every update.
            straight = tmp_path / mode / "straight"
            _train(_cfg(tmp_path / mode, run_dir=straight, total_updates=12, **extra))
            run = tmp_path / mode / "killed"
            killed_at = load_checkpoint(run / "checkpoint.pt")["state"]["updates"]
            assert 4 <= killed_at < 12, mode
            resumed = _train(
                _cfg(tmp_path / mode, run_dir=run, total_updates=12, checkpoint_interval=1,
                     resume=True, **extra)
            )  # fmt: skip
            assert_same_run(resumed, run, straight)


@settings(max_examples=60, deadline=None)
@given(
    n_envs=st.integers(1, 4),
    steps=st.integers(1, 30),
    p_end=st.sampled_from([0.0, 0.02, 0.15, 0.6]),
    cuts=st.lists(st.integers(1, 29), max_size=4),
    features=st.sampled_from([(), (1,), (2,)]),
    dtype=st.sampled_from([torch.float32, torch.float64, torch.bfloat16]),
    resume_at=st.integers(0, 5),
    seed=st.integers(0, 2**16),
)
def test_training_episode_returns_match_a_plain_loop_over_the_stream(
    n_envs, steps, p_end, cuts, features, dtype, resume_at, seed
):
    """Each ended episode's undiscounted return, whatever the segment cuts, with a
    checkpoint round trip between two segments, rewards with feature dimensions (summed)
    in any precision, and the mean popped every other segment."""
    generator = torch.Generator().manual_seed(seed)
    reward = torch.randn(n_envs, steps, *features, generator=generator).to(dtype)
    done = torch.rand(n_envs, steps, *features[:1], generator=generator) < p_end
    summed = reward.double().reshape(n_envs, steps, -1).sum(-1)
    ends, running = [], torch.zeros(n_envs, dtype=torch.float64)
    for t in range(steps):  # a plain loop over the whole stream
        running += summed[:, t]
        for i in range(n_envs):
            if done[i, t].any():
                ends.append((t, running[i].item()))
                running[i] = 0.0
    bounds = sorted({0, steps, *(c for c in cuts if c < steps)})
    tracker, popped_since = EpisodeReturns(carry=True), 0
    for k, (lo, hi) in enumerate(itertools.pairwise(bounds)):
        if k == resume_at:  # as a resumed run restores it from its checkpoint
            buffer = io.BytesIO()
            torch.save(tracker.state_dict(), buffer)
            buffer.seek(0)
            tracker = EpisodeReturns(carry=True)
            tracker.load_state_dict(torch.load(buffer))
        tracker.add(
            TensorDict(
                {"next": {"reward": reward[:, lo:hi], "done": done[:, lo:hi]}},
                batch_size=[n_envs, hi - lo],
            )
        )
        if k % 2 == 0 and hi < steps:
            continue
        expected = [value for t, value in ends if popped_since <= t < hi]
        recorded = [e for ended in tracker.state_dict()["ended"] for e in ended.tolist()]
        assert sorted(recorded) == pytest.approx(sorted(expected), rel=1e-9, abs=1e-9)
        mean = tracker.pop_mean()
        if expected:
            assert mean == pytest.approx(sum(expected) / len(expected), rel=1e-9, abs=1e-9)
        else:
            assert math.isnan(mean)
        popped_since = hi


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
@pytest.mark.parametrize("ends", [False, True])
def test_training_episode_returns_refuse_a_non_finite_reward(bad, ends):
    """Inside an episode that ends in the batch or one still in flight: the error names
    the reward and where it is, instead of a NaN mean in the logs."""
    reward = torch.ones(2, 5, 1)
    reward[1, 2] = bad
    done = torch.zeros(2, 5, 1, dtype=torch.bool)
    done[1, 4] = ends
    tracker = EpisodeReturns(carry=True)
    batch = TensorDict({"next": {"reward": reward, "done": done}}, batch_size=[2, 5])
    with pytest.raises(ValueError, match=r"reward holds 1 non-finite value\(s\) .*\(1, 2\)"):
        tracker.add(batch)


_HOLD_THE_LOCK = textwrap.dedent(
    """
    import sys, time
    from rl_pg.training import RunDirectory
    with RunDirectory({run!r}):
        print("locked", flush=True)
        time.sleep(60)
    """
)


class TestNothingIsLost:
    def test_a_second_run_on_the_same_directory_is_refused(self, tmp_path):
        run = tmp_path / "run"
        holder = subprocess.Popen(
            [sys.executable, "-c", _HOLD_THE_LOCK.format(run=str(run))],
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert holder.stdout.readline().strip() == "locked"
            with pytest.raises(
                RunDirBusy, match=f"in use by another run \\(process {holder.pid}\\)"
            ):
                _train(_cfg(tmp_path))
            assert not (run / "checkpoint.pt").exists()
        finally:
            holder.kill()
            holder.wait()
        # The holder died without unlocking: the kernel released its lock.
        assert _train(_cfg(tmp_path))["updates"] == 6

    def test_fresh_run_beside_the_leftovers_of_a_dead_one_is_refused(self, tmp_path):
        logs = tmp_path / "run" / "logs" / "csv" / "scalars" / "train"
        logs.mkdir(parents=True)
        (logs / "episode_return.csv").write_text("64,1.0\n")
        with pytest.raises(CheckpointError, match=r"holds \['logs'\] but no checkpoint"):
            _train(_cfg(tmp_path))
        assert (logs / "episode_return.csv").read_text() == "64,1.0\n"

    def test_a_run_that_fails_while_starting_leaves_no_directory(self, tmp_path):
        def broken_models(env):
            raise RuntimeError("no GPU here")

        with pytest.raises(RuntimeError, match="no GPU here"):
            train(_cfg(tmp_path), recipe="grid", make_env=make_grid, make_models=broken_models)
        assert not (tmp_path / "run").exists()

    def test_a_run_that_fails_at_its_first_update_leaves_no_directory(self, tmp_path):
        def models_without_trailing_value_dim(env):
            actor, _ = make_grid_models(env)
            flat = TensorDictModule(_Flatten(), ["observation"], ["state_value"])
            return actor, flat

        with pytest.raises(ValueError, match=r"writes 'state_value' of shape \(8, 2\)"):
            train(
                _cfg(tmp_path),
                recipe="grid",
                make_env=make_grid,
                make_models=models_without_trailing_value_dim,
            )
        assert not (tmp_path / "run").exists()
        assert _train(_cfg(tmp_path))["updates"] == 6  # the directory can be used at once

    def test_a_run_that_fails_while_training_keeps_its_logs(self, tmp_path):
        from rl_pg.training import Callback

        class FailAtThree(Callback):  # a NaN reward, a full disk, ...
            def on_update(self, run, batch, metrics):
                if run.state.updates == 3:
                    raise RuntimeError("disk full")

        cfg = _cfg(tmp_path, checkpoint_interval=1000)  # no checkpoint before it fails
        with pytest.raises(RuntimeError, match="disk full"):
            _train(cfg, callbacks=[FailAtThree()])
        run = tmp_path / "run"
        assert (run / "config.json").is_file() and not (run / "checkpoint.pt").exists()
        frames, _ = read_curve(run, "loss/actor")
        assert len(frames) == 3  # every update it made is in its logs
        with pytest.raises(CheckpointError, match=r"no checkpoint: its run stopped before"):
            _train(replace(cfg, resume=True))
        with pytest.raises(CheckpointError, match=r"but no checkpoint .*another --run-dir"):
            _train(cfg)
        assert len(read_curve(run, "loss/actor")[0]) == 3  # neither touched them

    def test_a_recipe_summary_that_fails_leaves_the_run_s_own_summary(self, tmp_path):
        def broken(run_dir):
            raise KeyError("a field the recipe expected")

        with pytest.raises(KeyError, match="a field the recipe expected"):
            train(_cfg(tmp_path, total_updates=2), recipe="grid", make_env=make_grid,
                  make_models=make_grid_models, summarise=broken)  # fmt: skip
        summary = json.loads((tmp_path / "run" / "summary.json").read_text())
        assert summary["updates"] == 2 and summary["sessions"][0]["frames_at_end"] > 0

    def test_runs_latest_names_the_newest_run(self, tmp_path, monkeypatch):
        monkeypatch.chdir(tmp_path)
        first = _train(_cfg(tmp_path, run_dir=None, total_updates=1, seed=1))
        latest = Path("runs/latest")
        assert latest.is_file() and resolve_latest(latest) == Path(first["run_dir"])
        second = _train(_cfg(tmp_path, run_dir=None, total_updates=1, seed=2))
        assert resolve_latest(latest) == Path(second["run_dir"])
        assert read_run(latest)["state"]["updates"] == 1  # commands take it as a run
        # a file, not a link: a walk of runs/ (TensorBoard's) meets each run once
        walked = [Path(d).name for d, _, files in os.walk("runs", followlinks=True)
                  if "checkpoint.pt" in files]  # fmt: skip
        assert sorted(walked) == sorted(Path(r["run_dir"]).name for r in (first, second))
        # a run in a directory of its own choosing leaves it alone
        _train(_cfg(tmp_path, run_dir=tmp_path / "runs" / "mine", total_updates=1))
        assert resolve_latest(latest) == Path(second["run_dir"])
        # the symbolic link of earlier versions is replaced by the file
        latest.unlink()
        latest.symlink_to(Path(first["run_dir"]).name, target_is_directory=True)
        third = _train(_cfg(tmp_path, run_dir=None, total_updates=1, seed=3))
        assert not latest.is_symlink() and resolve_latest(latest) == Path(third["run_dir"])
        # a real directory called latest is left alone
        latest.unlink()
        latest.mkdir()
        _train(_cfg(tmp_path, run_dir=None, total_updates=1, seed=4))
        assert latest.is_dir() and not any(latest.iterdir())
        # a latest file that names no run says so
        latest.rmdir()
        latest.write_text("../../etc\n")
        with pytest.raises(CheckpointError, match=r"holds '\.\./\.\./etc', which is none"):
            read_run(latest)

    def test_stale_temporary_files_are_removed(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2))
        stale = tmp_path / "run" / ".checkpoint.pt.x1y2.rl_pg-tmp"
        stale.write_bytes(b"half a checkpoint")
        _train(_cfg(tmp_path, total_updates=4, resume=True))
        assert not stale.exists()

    @pytest.mark.parametrize(
        ("override", "match"),
        [
            ({"total_updates": 4}, "already made 4 updates, and total_updates=4"),
            ({"total_updates": None, "total_frames": 50}, "already trained .* total_frames=50"),
        ],
    )
    def test_resume_with_no_budget_left_is_refused(self, tmp_path, override, match):
        _train(_cfg(tmp_path, total_updates=4))
        before = (tmp_path / "run" / "checkpoint.pt").read_bytes()
        with pytest.raises(CheckpointError, match=match):
            _train(_cfg(tmp_path, resume=True, **override))
        assert (tmp_path / "run" / "checkpoint.pt").read_bytes() == before

    def test_a_corrupted_checkpoint_is_never_resumed(self, tmp_path):
        _train(_cfg(tmp_path, total_updates=2))
        path = tmp_path / "run" / "checkpoint.pt"
        data = bytearray(path.read_bytes())
        middle = len(data) // 2
        data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
        path.write_bytes(bytes(data))
        with pytest.raises(CheckpointError, match="do not match the checksum"):
            _train(_cfg(tmp_path, total_updates=4, resume=True))
        with pytest.raises(CheckpointError, match="do not match the checksum"):
            read_run(tmp_path / "run")

    def test_torn_and_extra_log_rows_are_trimmed_on_resume(self, tmp_path):
        straight = _train(_cfg(tmp_path, run_dir=tmp_path / "straight", log_interval=1))
        _train(_cfg(tmp_path, total_updates=4, log_interval=1))
        csv = tmp_path / "run" / "logs" / "csv" / "scalars" / "loss" / "actor.csv"
        # What a run killed after its checkpoint leaves: rows past it, a row cut short.
        csv.write_text(csv.read_text() + "999999,0.5\n9999")
        _train(_cfg(tmp_path, total_updates=6, resume=True, log_interval=1))
        expected = tmp_path / "straight" / "logs" / "csv" / "scalars" / "loss" / "actor.csv"
        assert csv.read_text() == expected.read_text()
        assert straight["updates"] == 6

    def test_a_run_killed_while_trimming_its_logs_leaves_them_whole(self, tmp_path, monkeypatch):
        _train(_cfg(tmp_path, total_updates=4, log_interval=1))
        csv = tmp_path / "run" / "logs" / "csv" / "scalars" / "loss" / "actor.csv"
        untrimmed = csv.read_text() + "999999,0.5\n"
        csv.write_text(untrimmed)

        def killed(*args):  # the process dies just before the trimmed file replaces the old
            raise KeyboardInterrupt

        with monkeypatch.context() as patch:
            patch.setattr(os, "replace", killed)
            with pytest.raises(KeyboardInterrupt):
                _train(_cfg(tmp_path, total_updates=6, resume=True, log_interval=1))
        assert csv.read_text() == untrimmed  # whole, not half-written
        _train(_cfg(tmp_path, total_updates=6, resume=True, log_interval=1))
        assert "999999" not in csv.read_text()


class TestWhatTrainIsGiven:
    def test_run_dir_that_is_a_file(self, tmp_path):
        (tmp_path / "run").write_text("notes")
        with pytest.raises(RunDirUnusable, match="is a file; choose another --run-dir"):
            _train(_cfg(tmp_path))
        assert (tmp_path / "run").read_text() == "notes"

    def test_make_env_that_returns_no_environment(self, tmp_path):
        with pytest.raises(TypeError, match="make_env must return a TorchRL environment"):
            train(_cfg(tmp_path), recipe="grid", make_env=lambda: None, make_models=None)
        assert not (tmp_path / "run").exists()

    def test_make_models_that_returns_only_an_actor(self, tmp_path):
        with pytest.raises(TypeError, match=r"make_models must return \(actor, critic or None\)"):
            train(
                _cfg(tmp_path),
                recipe="grid",
                make_env=make_grid,
                make_models=lambda env: mlp_actor(env),
            )

    def test_a_config_that_is_not_a_train_config(self, tmp_path):
        with pytest.raises(TypeError, match="train needs a TrainConfig, got dict"):
            train({"lr": 0.1}, recipe="grid", make_env=make_grid, make_models=make_grid_models)

    def test_eval_flags_are_checked_before_training(self, tmp_path):
        with pytest.raises(TypeError, match="eval_flags must be a sequence of names"):
            _train(_cfg(tmp_path), eval_flags="crashed")
        assert not (tmp_path / "run").exists()

    def test_load_models_needs_a_checkpoint(self):
        with pytest.raises(CheckpointError, match="needs a checkpoint as read_run"):
            load_models({"weights": 1}, mlp_actor(make_grid()))


class _Flatten(nn.Module):
    """A value head that drops the trailing value dimension ([B] instead of [B, 1])."""

    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(16, 1)

    def forward(self, observation):
        return self.linear(observation).squeeze(-1)


class TestBufferedCSVLogs:
    """The CSV logs are TorchRL's rows, written in bulk but on disk whenever the run
    checkpoints, evaluates or ends."""

    CALLS = (  # name, value, step (None: TorchRL counts the scalar's rows)
        ("loss/actor", 0.5, 128), ("eval/mean_return", -3.25, 256),
        ("loss/actor", 1e-9, 384), ("loss/actor", float("nan"), 512),
        ("count", 7, None), ("count", 8, None),
    )  # fmt: skip

    def test_the_files_hold_torchrls_own_rows(self, tmp_path):
        ours = BufferedCSVLogger("csv", str(tmp_path / "ours"), flush_every=3600.0)
        theirs = CSVLogger("csv", str(tmp_path / "theirs"))
        for name, value, step in self.CALLS:
            ours.log_scalar(name, value, step=step)
            theirs.log_scalar(name, value, step=step)
        ours.flush()

        def files(root):
            return {p.relative_to(root): p.read_bytes() for p in root.rglob("*.csv")}

        assert files(tmp_path / "ours") == files(tmp_path / "theirs")
        assert len(files(tmp_path / "ours")) == 3

    def test_rows_wait_for_a_flush_or_their_deadline(self, tmp_path):
        held = BufferedCSVLogger("csv", str(tmp_path / "held"), flush_every=3600.0)
        held.log_scalar("a", 1.0, step=1)
        path = tmp_path / "held" / "csv" / "scalars" / "a.csv"
        assert path.read_text() == ""
        held.flush()
        assert path.read_text() == "1,1.0\n"
        for bad, error in ((-1.0, ValueError), (float("nan"), ValueError), ("1", TypeError)):
            with pytest.raises(error, match="flush_every"):
                BufferedCSVLogger("csv", str(tmp_path / "bad"), flush_every=bad)
        eager = BufferedCSVLogger("csv", str(tmp_path / "eager"), flush_every=0.0)
        eager.log_scalar("a", 2.0, step=3)
        assert (tmp_path / "eager" / "csv" / "scalars" / "a.csv").read_text() == "3,2.0\n"

    def test_every_row_is_on_disk_when_the_run_checkpoints_and_when_it_ends(self, tmp_path):
        seen = []

        class ReadTheLogs(Callback):
            def on_checkpoint(self, run):
                seen.append((run.state.frames, read_curve(run.path, "loss/actor")[0][-1]))

            def on_end(self, run):
                seen.append((run.state.frames, read_curve(run.path, "loss/actor")[0][-1]))

        _train(_cfg(tmp_path, total_updates=5, checkpoint_interval=2), callbacks=[ReadTheLogs()])
        assert len(seen) == 4  # at updates 2, 4 and 5 (the last), then at the end
        assert all(frames == last_logged for frames, last_logged in seen)


def test_curves_are_read_from_logs_cut_short_by_a_kill(tmp_path):
    _train(_cfg(tmp_path, total_updates=2, log_interval=1))
    csv = tmp_path / "run" / "logs" / "csv" / "scalars" / "loss" / "actor.csv"
    complete = csv.read_text()
    csv.write_text(complete + "1234,0.2")  # the last row lost its end
    steps, values = read_curve(tmp_path / "run", "loss/actor")
    assert len(steps) == len(values) == complete.count("\n")


def test_training_leaves_the_matplotlib_backend_alone(tmp_path):
    import matplotlib

    before = matplotlib.get_backend()
    matplotlib.use("svg")  # e.g. a notebook's inline backend
    try:
        _train(_cfg(tmp_path, total_updates=1))
        assert matplotlib.get_backend() == "svg"
        assert (tmp_path / "run" / "learning_curve.png").read_bytes()[:4] == b"\x89PNG"
    finally:
        matplotlib.use(before)


class TestInterruptedRun:
    """Ctrl-C: the update in progress ends, the run saves and says how to resume."""

    FLAGS = ("--checkpoint-interval", "1000000", "--eval-interval", "100000000")

    def test_ctrl_c_or_kill_saves_resumes_and_reaches_the_workers(self, tmp_path):
        # Three runs as a user starts them, side by side (most of their time is imports):
        # - "single": a gridworld run stopped by a plain `kill` (SIGTERM), then resumed;
        # - "workers": CartPole on two worker processes, interrupted as a terminal does,
        #   by signalling SIGINT to the whole process group, and "workers-term" the same
        #   with SIGTERM, as a batch scheduler may: the workers must leave the stop to
        #   the main process instead of dying under it.
        recipes = Path(__file__).resolve().parents[1] / "recipes"
        runs = {name: tmp_path / name for name in ("single", "workers", "workers-term")}
        cartpole = [sys.executable, str(recipes / "cartpole.py"), "--workers", "2",
                    "--total-frames", "100000000", "--threshold", "100000"]  # fmt: skip
        commands = {
            "single": [sys.executable, str(recipes / "gridworld.py"), "--total-updates", "100000"],
            "workers": cartpole,
            "workers-term": cartpole,
        }
        sent = {"single": signal.SIGTERM, "workers": signal.SIGINT, "workers-term": signal.SIGTERM}
        processes = {
            name: subprocess.Popen(
                [*command, "--run-dir", str(runs[name]), "--no-progress", *self.FLAGS],
                stderr=subprocess.PIPE,
                text=True,
                start_new_session=name != "single",
            )
            for name, command in commands.items()
        }
        stderr = {}
        try:
            _signal_when_ready(
                processes,
                lambda name: _lines(runs[name] / "logs/csv/scalars/loss/actor.csv") >= 3,
                lambda name, process: (
                    process.send_signal(sent[name])
                    if name == "single"
                    else os.killpg(process.pid, sent[name])
                ),
                timeout=180,
            )
            for name, process in processes.items():
                stderr[name] = process.communicate(timeout=120)[1]
        finally:
            for process in processes.values():
                process.kill()
                process.wait()
        for name, process in processes.items():
            assert process.returncode == 130, stderr[name]
            assert "Traceback" not in stderr[name]
            assert f"Interrupted ({sent[name].name}) at" in stderr[name]
            assert f"Continue with: rl-pg resume {runs[name]}" in stderr[name]

        run = runs["single"]
        summary = json.loads((run / "summary.json").read_text())
        assert summary["interrupted"] is True
        stopped_at = load_checkpoint(run / "checkpoint.pt")["state"]["updates"]
        assert summary["updates"] == stopped_at >= 3
        gridworld = load("gridworld")
        common = {"checkpoint_interval": 1_000_000, "eval_interval": 100_000_000}
        common.update(progress=False, total_updates=stopped_at + 3)
        gridworld.train(gridworld.config(run_dir=tmp_path / "straight", **common))
        resumed = gridworld.train(gridworld.config(run_dir=run, resume=True, **common))
        assert resumed["interrupted"] is False
        assert_same_run(resumed, run, tmp_path / "straight")

    @pytest.mark.parametrize("where", ["stop_training", "checkpoint_due"])
    def test_a_stop_landing_anywhere_in_an_update_still_leaves_its_checkpoint(
        self, tmp_path, where
    ):
        # A signal can land between any two bytecodes; here it lands in a callback called
        # after the loop decided the update (`stop_training`) or while it asks whether a
        # checkpoint is due (`checkpoint_due`). Either way the run must end on a
        # checkpoint of the update its summary reports.
        class SignalAt(Callback):
            def _maybe_signal(self, run, name):
                if name == where and run.state.updates == 2:
                    os.kill(os.getpid(), signal.SIGTERM)
                return False

            def stop_training(self, run):
                return self._maybe_signal(run, "stop_training")

            def checkpoint_due(self, run):
                return self._maybe_signal(run, "checkpoint_due")

        cfg = _cfg(tmp_path, total_updates=50, checkpoint_interval=1_000)
        with pytest.raises(KeyboardInterrupt):
            _train(cfg, callbacks=[SignalAt()])
        summary = json.loads((tmp_path / "run" / "summary.json").read_text())
        assert summary["interrupted"] is True and summary["updates"] in (2, 3)
        saved = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
        assert saved["state"]["updates"] == summary["updates"]

    def test_a_stop_is_kept_when_a_library_took_the_signals_during_the_run(self, tmp_path):
        # ray.init (the Ray collectors and evaluators) sets a SIGTERM handler that ends
        # the process at once; a library doing so while the run starts or runs must not
        # cost the run its stop: the next update takes the signals back.
        class LibraryTakesSignals(Callback):
            def on_start(self, run):
                for sig in (signal.SIGTERM, signal.SIGINT):
                    signal.signal(sig, lambda *_: sys.exit(15))

            def on_update(self, run, batch, metrics):
                if run.state.updates == 2:
                    signal.signal(signal.SIGTERM, lambda *_: sys.exit(15))  # again, mid-run
                if run.state.updates == 3:
                    os.kill(os.getpid(), signal.SIGTERM)

        with pytest.raises(KeyboardInterrupt):
            _train(_cfg(tmp_path, total_updates=50, checkpoint_interval=1_000),
                   callbacks=[LibraryTakesSignals()])  # fmt: skip
        summary = json.loads((tmp_path / "run" / "summary.json").read_text())
        assert summary["interrupted"] is True and summary["updates"] in (3, 4)
        saved = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
        assert saved["state"]["updates"] == summary["updates"]

    def test_a_stop_once_the_budget_is_spent_lets_the_run_finish(self, tmp_path, capsys):
        # Landing during the last update's evaluation, the signal cuts nothing short: the
        # run ends as it would have, not as one to resume.
        class SignalAtTheEnd(Callback):
            def on_evaluation(self, run, metrics):
                if run.budget_spent():
                    os.kill(os.getpid(), signal.SIGTERM)

        summary = _train(_cfg(tmp_path, total_updates=3), callbacks=[SignalAtTheEnd()])
        assert summary["interrupted"] is False and summary["updates"] == 3
        assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["state"]["updates"] == 3
        assert "Interrupted" not in capsys.readouterr().err

    @pytest.mark.parametrize(
        ("first", "second"),
        [
            (signal.SIGINT, signal.SIGINT),
            (signal.SIGTERM, signal.SIGTERM),
            (signal.SIGTERM, signal.SIGINT),
            (signal.SIGHUP, signal.SIGHUP),
        ],
    )
    def test_a_second_stop_stops_at_once(self, first, second):
        from rl_pg.training.interrupt import InterruptRequest

        before = {
            sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
        }
        with InterruptRequest() as interrupt:
            try:
                os.kill(os.getpid(), first)  # the first: only a request
            except KeyboardInterrupt:
                pytest.fail(f"the first {first.name} stopped at once instead of asking to stop")
            assert interrupt.requested and interrupt.signal_name == first.name
            with pytest.raises(KeyboardInterrupt):
                os.kill(os.getpid(), second)  # the second: stops at once
        for sig, handler in before.items():
            assert signal.getsignal(sig) is handler  # restored

    def test_the_command_exits_holding_nothing_the_interrupted_run_built(self):
        # What a stopped run's frames hold (its environments) must be freed before the
        # process freezes its heap and exits: a simulator's bindings report what is
        # still alive then as leaked (Pong's 16 games did, after a SIGTERM).
        import weakref

        from rl_pg.training.interrupt import exit_quietly_on_interrupt

        class Environment:
            pass

        def interrupted_run():
            env = Environment()
            held.append(weakref.ref(env))
            raise KeyboardInterrupt

        held = []
        with pytest.raises(SystemExit) as stop, exit_quietly_on_interrupt():
            interrupted_run()
        assert stop.value.code == 130
        assert held[0]() is None, "the interrupted run's frame still holds its environment"


class TestConsole:
    def test_lines_when_not_on_a_terminal(self, tmp_path):
        stream = io.StringIO()
        console = Console(total_frames=1000, initial_frames=0, enabled=True, stream=stream)
        console.update(100, 100, {"train/episode_return": 3.0, "loss/actor": 0.5}, {})
        console.update(200, 100, None, {"eval/mean_return": 7.0}, evaluated=True)
        lines = stream.getvalue().splitlines()
        assert len(lines) == 1  # the first update came before every_s had passed
        assert "frames 200/1,000" in lines[0] and "train return 3.00" in lines[0]
        assert "eval 7.00" in lines[0]

    def test_progress_counts_to_the_limit_that_ends_the_run(self):
        stream = io.StringIO()  # an update budget that ends the run at 2,000 frames
        console = Console(
            total_frames=10_000_000, initial_frames=0, enabled=True, stream=stream,
            total_updates=200,
        )  # fmt: skip
        console.update(500, 500, None, {}, evaluated=True, updates=50)
        assert "frames 500/2,000 | update 50/200 |" in stream.getvalue()
        bar = Console(total_frames=10_000, initial_frames=0, enabled=True, stream=stream,
                      total_updates=10**6)  # fmt: skip
        bar.update(100, 100, None, {}, evaluated=True, updates=1)  # frames end it first
        assert "frames 100/10,000 | update 1/1,000,000 |" in stream.getvalue()

    def test_nothing_when_disabled(self):
        stream = io.StringIO()
        console = Console(total_frames=10, initial_frames=0, enabled=False, stream=stream)
        console.update(10, 10, None, {}, evaluated=True)
        console.close()
        assert stream.getvalue() == ""

    def test_a_recipe_in_a_pipe_reports_progress_and_a_readable_summary(self, tmp_path):
        recipes = Path(__file__).resolve().parents[1] / "recipes"
        flags = ["--run-dir", str(tmp_path / "r"), "--total-updates", "3", "--eval-interval", "500"]
        result = subprocess.run(
            [sys.executable, str(recipes / "gridworld.py"), *flags],
            capture_output=True,
            text=True,
            check=True,
        )
        assert "frames " in result.stderr and "eval " in result.stderr  # one line per eval
        assert result.stdout.startswith("gridworld, seed 0: ")
        assert f"run directory: {tmp_path / 'r'}" in result.stdout


class TestResumeFromTheCommandLine:
    def test_resume_needs_only_the_run_directory_and_what_changes(self, tmp_path, capsys):
        # `python recipes/gridworld.py FLAGS` is this command (tests/test_cli.py), and a
        # fresh process resumes from the directory alone there too.
        from rl_pg.app.cli import main

        run = str(tmp_path / "run")
        first = ["--run-dir", run, "--total-updates", "2", "--lr", "0.05", "--hidden", "16"]
        main(["train", "gridworld", *first, "--no-progress"])
        stored = json.loads((tmp_path / "run" / "config.json").read_text())
        assert (stored["recipe"], stored["lr"], stored["hidden"]) == ("gridworld", 0.05, 16)
        main(["train", "gridworld", "--resume", "--run-dir", run, "--total-updates", "4"])
        capsys.readouterr()
        assert json.loads((tmp_path / "run" / "summary.json").read_text())["updates"] == 4
        assert json.loads((tmp_path / "run" / "config.json").read_text())["total_updates"] == 4


class TestDevice:
    def test_auto_trains_where_torch_can(self, tmp_path):
        summary = _train(_cfg(tmp_path, device="auto", total_updates=2))
        expected = "cuda" if torch.cuda.is_available() else "cpu"
        assert summary["updates"] == 2
        assert _cfg(tmp_path, device="auto").torch_device().type == expected
        assert all(v.device.type == "cpu" for v in run_weights(tmp_path / "run").values())

    @pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
    def test_cuda_without_a_gpu_says_so_before_anything_starts(self, tmp_path):
        with pytest.raises(ValueError, match=r"--device\) is 'cuda' but torch sees no CUDA"):
            _train(_cfg(tmp_path, device="cuda"))
        assert not (tmp_path / "run").exists()

    def test_cuda_with_worker_processes_is_refused(self, tmp_path):
        cfg = _cfg(tmp_path, device="cuda", workers=2)
        with pytest.raises(ValueError, match="local collection only: drop --workers"):
            cfg.torch_device()


def test_keep_every_keeps_copies_without_changing_the_run(tmp_path):
    plain = _cfg(tmp_path, run_dir=tmp_path / "plain", total_updates=5, **SEGMENTS)
    _train(plain)
    _train(replace(plain, run_dir=tmp_path / "kept", keep_every=2))
    kept = sorted((tmp_path / "kept" / "checkpoints").glob("*.pt"))
    assert [p.name for p in kept] == ["update_2.pt", "update_4.pt"]
    assert [read_run(p)["state"]["updates"] for p in kept] == [2, 4]
    assert not (tmp_path / "plain" / "checkpoints").exists()
    for key, value in run_weights(tmp_path / "plain").items():
        assert torch.equal(value, run_weights(tmp_path / "kept")[key]), key


def test_worker_factories_leave_the_main_process_ctrl_c_alone():
    from rl_pg.training.interrupt import InterruptRequest, MainProcessInterrupts

    with InterruptRequest() as interrupt:
        before = signal.getsignal(signal.SIGINT)
        MainProcessInterrupts(make_grid)()  # as ParallelEnv does to read specs
        assert signal.getsignal(signal.SIGINT) is before
        os.kill(os.getpid(), signal.SIGINT)
        assert interrupt.requested


class TestSessions:
    """The summary records each session of a run: frames, code, libraries, machine."""

    def test_a_resumed_run_lists_both_sessions(self, tmp_path):
        import subprocess

        import torch as torch_module

        import rl_pg

        first = _train(_cfg(tmp_path, total_updates=2))
        (session,) = first["sessions"]
        assert session["frames_at_start"] == 0
        assert session["frames_at_end"] == first["frames"] > 0
        assert session["interrupted"] is False
        assert session["code"]["rl_pg"] == rl_pg.__version__
        assert session["libraries"]["torch"] == torch_module.__version__
        assert session["machine"]["cores"] == os.cpu_count()
        repo = Path(rl_pg.__file__).resolve().parents[1]
        if (repo / ".git").exists():  # a checkout (CI's clean clone is one)
            git = ["git", "-C", str(repo), "rev-parse", "HEAD"]
            head = subprocess.run(git, capture_output=True, text=True, check=True).stdout.strip()
            assert session["code"]["commit"] == head
        second = _train(_cfg(tmp_path, total_updates=4, resume=True))
        earlier, latest = second["sessions"]
        assert earlier == session
        assert latest["frames_at_start"] == first["frames"]
        assert latest["frames_at_end"] == second["frames"] > first["frames"]
        assert latest["changed"] == {"total_updates": [2, 4]}
        from rl_pg.training.console import format_summary

        printed = format_summary(second)  # what the console prints: counts, not records
        assert "sessions: 2 (stopped and resumed once)" in printed
        assert "None" not in printed and "'code'" not in printed
        # a summary that cannot be read does not stop the run; its sessions are lost
        (tmp_path / "run" / "summary.json").write_text("{torn")
        third = _train(_cfg(tmp_path, total_updates=5, resume=True))
        assert [s["frames_at_start"] for s in third["sessions"]] == [second["frames"]]

    def test_a_resume_that_changes_the_results_says_so(self, tmp_path, capsys):
        _train(_cfg(tmp_path, total_updates=2))
        capsys.readouterr()
        summary = _train(_cfg(tmp_path, total_updates=3, resume=True, threads=2))
        err = capsys.readouterr().err
        assert "Resuming with threads 1 -> 2: the run goes on" in err
        assert summary["sessions"][-1]["changed"] == {"total_updates": [2, 3], "threads": [1, 2]}
        _train(_cfg(tmp_path, total_updates=4, resume=True, threads=2))
        assert "Resuming with" not in capsys.readouterr().err  # nothing changed this time


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads /proc (Linux)")
def test_processes_started_for_ray_leave_a_group_stop_to_the_run():
    # Ray's GCS, raylet and workers start inside signal_handlers_kept(): with SIGTERM and
    # SIGHUP blocked, a `kill -TERM -PGID` reaches the run (which saves, then shuts Ray
    # down) and not them; this process's own mask and handlers are as they were.
    from rl_pg._process import signal_handlers_kept

    def blocked(status: str) -> set[int]:
        mask = int(re.search(r"^SigBlk:\s*(\w+)$", status, re.MULTILINE)[1], 16)
        return {sig for sig in range(1, 64) if mask >> (sig - 1) & 1}

    handler = signal.getsignal(signal.SIGTERM)
    with signal_handlers_kept():
        child = subprocess.Popen(["sleep", "5"])
    try:
        status = Path(f"/proc/{child.pid}/status").read_text()
        assert {signal.SIGTERM, signal.SIGHUP} <= blocked(status)
    finally:
        child.kill()
        child.wait()
    assert signal.SIGTERM not in blocked(Path("/proc/self/status").read_text())
    assert signal.getsignal(signal.SIGTERM) is handler
