"""How close does rl_pg's training loop run to the speed of its environments?

One run, every contender timed in turn, repetitions interleaved (so machine noise hits
all alike), medians of frames/s reported with ratios to the floor measured in the same
run at the same number of environments. The learning loops of one task and number of
environments (rl_pg's and the plain-PyTorch ones) train the same frames per repetition,
repetition k from seed k: how fast a loop runs depends on where its training is (short
early episodes reset the environments more often) and on the seed's trajectory.

* rl_pg's training loop: a recipe with its defaults except the number of environments
  and the backend (collection, returns, loss, optimiser step; evaluation excluded),
  frames / training wall-clock.
* The floors, what the environments cost with no framework and no learning:
  CartPole: plain gymnasium ``SyncVectorEnv`` (or EnvPool) stepped by the recipe's
  MLP policy (sampled actions, no TensorDict); LunarLander: the vectorised landers
  stepped with uniformly random actions.
* rl_pg's loop with ``--overlap`` (EnvPool, two halves of the pool stepping in turn
  while the policy acts on the other half), against the same floors and the plain loop.
* Collection alone, in segments of the recipe's length with its lean policy: TorchRL's
  ``Collector`` (no trajectory ids) against rl_pg's ``SegmentCollector``, which the
  recipes use and which gives the same batches.
* The same plain loop with a CleanRL script's bookkeeping (episode statistics and
  per-update scalars written to TensorBoard), when TensorBoard is installed: what a
  hand-written loop costs once it reports what it does, as rl_pg's does.
* For context: TorchRL's stock ``Collector(GymEnv("CartPole-v1"))`` (collection only,
  same MLP policy) and Stable-Baselines3 A2C's training loop (8 environments).

EnvPool contenders run when EnvPool is installed (``pip install -e ".[envpool]"``).

    pip install -c constraints.txt -e ".[bench,envpool]"
    python benchmarks/throughput.py
"""

from __future__ import annotations

import importlib.util
import statistics
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
import tyro
from common import REPO, ratio_interval, table, write_json
from torchrl.collectors import Collector
from torchrl.envs import GymEnv

from rl_pg.collectors import SegmentCollector
from rl_pg.envs.envpool import BOX_CAST_WARNING
from rl_pg.functional import reward_to_go
from rl_pg.lean import lean_policy
from rl_pg.recipes import load

cartpole, lunarlander = load("cartpole"), load("lunarlander")
HAS_ENVPOOL = importlib.util.find_spec("envpool") is not None
HAS_TENSORBOARD = importlib.util.find_spec("tensorboard") is not None


@dataclass
class Config:
    """Training frames/s of rl_pg's loop against its environments' own speed."""

    seconds: float = 3.0
    """Target duration of one repetition of one contender."""
    repeats: int = 3
    """Interleaved repetitions per contender (the median is reported)."""
    probe_frames: int = 2_000
    """Frames of the first, untimed-for-the-result run that sizes each repetition."""
    cartpole_envs: list[int] = field(default_factory=lambda: [8, 32])
    """CartPole environment counts compared (32 is the recipe's default)."""
    lunarlander_envs: list[int] = field(default_factory=lambda: [8])
    """LunarLander environment counts compared (8 is the recipe's default)."""
    peers: bool = True
    """Also time TorchRL's stock collector and SB3 A2C (context, no ratio target)."""
    threads: int = 1
    """torch threads for every contender."""
    json_path: Path = REPO / "benchmarks/results/throughput.json"
    """Where the results are written."""


def recipe_training(recipe, **overrides) -> Callable[..., float]:
    """The recipe's training loop for ``frames`` from ``seed`` (default 0): frames per
    second of its training wall-clock."""

    def run(frames: int, seed: int = 0) -> float:
        with tempfile.TemporaryDirectory() as run_dir:
            summary = recipe.train(
                recipe.config(
                    run_dir=Path(run_dir),
                    seed=seed,
                    total_frames=frames,
                    threshold=None,
                    eval_interval=10**12,  # one evaluation, at the end, outside the timer
                    eval_episodes=1,
                    checkpoint_interval=10**12,
                    progress=False,
                    **overrides,
                )
            )
        return summary["frames"] / summary["train_wall_s"]

    return run


def _vector(env_id: str, n: int, backend: str, **kwargs):
    if backend == "envpool":
        import envpool

        return envpool.make_gymnasium(env_id, num_envs=n, seed=0, **kwargs)
    return gym.make_vec(env_id, num_envs=n, vectorization_mode="sync", **kwargs)


def cartpole_floor(n: int, backend: str) -> Callable[[int], float]:
    """The recipe's MLP stepping ``n`` CartPoles: no TensorDict, no learning."""

    def run(frames: int) -> float:
        envs = _vector("CartPole-v1", n, backend)
        recipe = cartpole.config()
        actor = cartpole.make_models(cartpole.make_env(recipe), recipe)[0]
        net = actor.module[0].module  # the policy's plain nn.Module (logits)
        obs, _ = envs.reset(seed=0) if backend == "gymnasium" else envs.reset()
        steps = max(1, frames // n)
        start = time.perf_counter()
        with torch.inference_mode():
            for _ in range(steps):
                logits = net(torch.as_tensor(obs))
                action = torch.distributions.Categorical(logits=logits).sample()
                obs, *_ = envs.step(action.numpy())
        rate = steps * n / (time.perf_counter() - start)
        envs.close()
        return rate

    return run


def random_floor(env_id: str, n: int, backend: str) -> Callable[[int], float]:
    """``n`` environments stepped with uniformly random actions."""

    def run(frames: int) -> float:
        envs = _vector(env_id, n, backend)
        envs.reset()
        rng = np.random.default_rng(0)
        steps = max(1, frames // n)
        count = envs.single_action_space.n
        actions = rng.integers(0, count, size=(steps, n))
        start = time.perf_counter()
        for action in actions:
            envs.step(action)
        rate = steps * n / (time.perf_counter() - start)
        envs.close()
        return rate

    return run


class PlainLoop:
    """The recipe's algorithm written out in plain PyTorch over gymnasium's vector env:
    what the same work costs with no TensorDict, no TorchRL and no run bookkeeping.

    The same networks, segments, reward-to-go bootstrapped from the critic, value-loss
    weight, entropy bonus, advantage standardisation, gradient clipping and fused Adam
    as the recipe's defaults; one optimiser step per segment. It is a cost reference:
    finished episodes are treated as terminated (no truncation bootstrap) and no
    episode statistics are kept. Its pieces (``act``, ``step``, ``batch``, ``loss``,
    ``optimise``) are methods so that ``breakdown.py`` can time them apart. With a
    ``seed``, torch's generator (the networks' initialisation, the sampled actions) and
    the environments start from it; without one, the environments from 0 and torch's
    generator from wherever it is.
    """

    def __init__(self, recipe, n: int, seed: int | None = None) -> None:
        self.cfg = cfg = recipe.config(num_envs=n)
        if seed is not None:  # the networks' initialisation and the sampled actions
            torch.manual_seed(seed)
        self.env_seed = seed or 0
        sizing = recipe.make_env(cfg)
        actor, critic = recipe.make_models(sizing, cfg)
        sizing.close()
        self.policy_net, self.value_net = actor.module[0].module, critic.module
        self.params = [*self.policy_net.parameters(), *self.value_net.parameters()]
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.lr, fused=True)
        self.envs = gym.make_vec(
            getattr(cfg, "env_id", "LunarLander-v3"),
            num_envs=n,
            vectorization_mode="sync",
            vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP},
        )
        self.obs, _ = self.envs.reset(seed=self.env_seed)

    def act(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The current observations and the actions sampled for them."""
        observation = torch.as_tensor(self.obs)
        with torch.no_grad():
            action = torch.distributions.Categorical(logits=self.policy_net(observation))
            return observation, action.sample()

    def step(self, observation: torch.Tensor, action: torch.Tensor) -> tuple:
        """Steps the environments (finished ones reset in the same call); the step."""
        self.obs, reward, terminated, truncated, _ = self.envs.step(action.numpy())
        return observation, action, torch.as_tensor(reward), torch.as_tensor(terminated | truncated)

    def batch(self, segment: list[tuple]) -> tuple[torch.Tensor, ...]:
        """The segment's steps stacked, time first, and the observations after it."""
        observation, action, reward, done = (torch.stack(x) for x in zip(*segment, strict=True))
        last = torch.as_tensor(self.obs)
        return observation, action, reward.float().unsqueeze(-1), done.unsqueeze(-1), last

    def terms(self, observation, action, reward, done, last) -> tuple[torch.Tensor, ...]:
        """The policy loss, the value loss, the entropy, the values and the returns."""
        cfg, value_net = self.cfg, self.value_net
        with torch.no_grad():
            next_value = value_net(torch.cat([observation[1:], last.unsqueeze(0)]))
            returns = reward_to_go(reward, done, cfg.gamma, time_dim=0, next_value=next_value)
        value = value_net(observation)
        advantage = returns - value.detach()
        if cfg.normalize_advantage:
            advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
        dist = torch.distributions.Categorical(logits=self.policy_net(observation))
        policy_loss = -(dist.log_prob(action).unsqueeze(-1) * advantage).mean()
        value_loss = (value - returns).pow(2).mean()
        return policy_loss, value_loss, dist.entropy().mean(), value.detach(), returns

    def loss(self, *batch: torch.Tensor) -> torch.Tensor:
        return self.combine(self.terms(*batch))

    def combine(self, terms: tuple[torch.Tensor, ...]) -> torch.Tensor:
        """The loss of ``terms``: the policy loss, the entropy bonus, the value loss."""
        policy_loss, value_loss, entropy, *_ = terms
        cfg = self.cfg
        return policy_loss - cfg.entropy_coeff * entropy + cfg.critic_coeff * value_loss

    def optimise(self, loss: torch.Tensor) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.cfg.max_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_(self.params, self.cfg.max_grad_norm, foreach=True)
        self.optimizer.step()


class BookkeepingLoop(PlainLoop):
    """``PlainLoop`` with the bookkeeping of a CleanRL script: gymnasium's
    ``RecordEpisodeStatistics`` on the vector env, each finished episode's return and
    length written to TensorBoard, and per update the learning rate, the policy, value
    and entropy losses, the explained variance and the frames per second. Still no
    truncation bootstrap (CleanRL has none) and no checkpoints or evaluations."""

    def __init__(self, recipe, n: int, log_dir: str, seed: int | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        super().__init__(recipe, n, seed)
        self.envs = gym.wrappers.vector.RecordEpisodeStatistics(self.envs)
        self.obs, _ = self.envs.reset(seed=self.env_seed)
        self.writer = SummaryWriter(log_dir)
        self.frames, self.start = 0, time.perf_counter()

    def step(self, observation: torch.Tensor, action: torch.Tensor) -> tuple:
        self.obs, reward, terminated, truncated, infos = self.envs.step(action.numpy())
        self.frames += len(reward)
        if "episode" in infos:  # as CleanRL reads it
            for i in np.flatnonzero(infos["_episode"]):
                self.writer.add_scalar(
                    "charts/episodic_return", infos["episode"]["r"][i], self.frames
                )
                self.writer.add_scalar(
                    "charts/episodic_length", infos["episode"]["l"][i], self.frames
                )
        return observation, action, torch.as_tensor(reward), torch.as_tensor(terminated | truncated)

    def loss(self, *batch: torch.Tensor) -> torch.Tensor:
        self.logged = self.terms(*batch)
        return self.combine(self.logged)

    def optimise(self, loss: torch.Tensor) -> None:
        super().optimise(loss)
        policy_loss, value_loss, entropy, value, returns = self.logged
        y_pred, y_true = value.numpy(), returns.numpy()
        var_y = np.var(y_true)
        explained = np.nan if var_y == 0 else 1 - np.var(y_true - y_pred) / var_y
        lr = self.optimizer.param_groups[0]["lr"]
        for tag, scalar in (
            ("charts/learning_rate", lr),
            ("losses/value_loss", value_loss.item()),
            ("losses/policy_loss", policy_loss.item()),
            ("losses/entropy", entropy.item()),
            ("losses/explained_variance", explained),
            ("charts/SPS", self.frames / (time.perf_counter() - self.start)),
        ):
            self.writer.add_scalar(tag, scalar, self.frames)  # fmt: skip


def plain_pytorch_training(recipe, n: int, bookkeeping: bool = False) -> Callable[..., float]:
    """``PlainLoop`` (or with ``bookkeeping``, ``BookkeepingLoop``) trained for
    ``frames`` from ``seed`` (default 0): frames per second."""

    def run(frames: int, seed: int = 0) -> float:
        with tempfile.TemporaryDirectory() as log_dir:
            if not bookkeeping:
                return _plain_rate(PlainLoop(recipe, n, seed), frames)
            loop = BookkeepingLoop(recipe, n, log_dir, seed)
            try:
                return _plain_rate(loop, frames)
            finally:  # its writer's thread would write into the deleted directory
                loop.writer.close()

    return run


def _plain_rate(plain: PlainLoop, frames: int) -> float:
    """Frames per second of ``plain`` trained for about ``frames``."""
    steps, n = plain.cfg.segment_length, plain.cfg.num_envs
    updates = max(1, frames // (steps * n))
    start = time.perf_counter()
    for _ in range(updates):
        segment = [plain.step(*plain.act()) for _ in range(steps)]
        plain.optimise(plain.loss(*plain.batch(segment)))
    rate = updates * steps * n / (time.perf_counter() - start)
    plain.envs.close()
    return rate


def collection_only(recipe, n: int, kind: str) -> Callable[[int], float]:
    """The recipe's environments and lean policy, collected in segments by TorchRL's
    ``Collector`` (as tuned in the docs: no trajectory ids) or by rl_pg's
    ``SegmentCollector``, which gives the same batches; no learning."""

    def run(frames: int) -> float:
        cfg = recipe.config(num_envs=n)
        env = recipe.make_env(cfg)
        policy = lean_policy(recipe.make_models(env, cfg)[0])
        per_batch = n * cfg.segment_length
        if kind == "SegmentCollector":
            collector = SegmentCollector(env, policy, per_batch)
        else:
            collector = Collector(
                env,
                policy,
                frames_per_batch=per_batch,
                total_frames=-1,
                track_traj_ids=False,
                auto_register_policy_transforms=False,
            )
        return _collection_rate(collector, frames)

    return run


def torchrl_collector(frames: int) -> float:
    recipe = cartpole.config()
    actor = cartpole.make_models(cartpole.make_env(recipe), recipe)[0]
    env = GymEnv("CartPole-v1", categorical_action_encoding=True)
    collector = Collector(
        env, actor, frames_per_batch=200, total_frames=-1, auto_register_policy_transforms=False
    )
    return _collection_rate(collector, frames)


def _collection_rate(collector, frames: int) -> float:
    """Frames per second of ``collector`` over about ``frames`` frames (its first batch,
    the start-up, untimed); shuts it down."""
    iterator = iter(collector)
    next(iterator)
    start, done = time.perf_counter(), 0
    while done < frames:
        done += next(iterator).numel()
    rate = done / (time.perf_counter() - start)
    collector.shutdown()
    return rate


def sb3_a2c(frames: int) -> float:
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env

    model = A2C("MlpPolicy", make_vec_env("CartPole-v1", n_envs=8, seed=0), seed=0, device="cpu")
    start = time.perf_counter()
    model.learn(total_timesteps=frames)
    return model.num_timesteps / (time.perf_counter() - start)


def contenders(
    cfg: Config,
) -> tuple[dict[str, Callable[..., float]], list[tuple[str, str]], dict[str, str]]:
    """The runs to time, the (loop, floor) pairs whose ratio is reported, and the
    training loops' cohorts (a task at a number of environments): the loops of one
    cohort are timed on the same frames from the same seeds."""
    runs: dict[str, Callable[..., float]] = {}
    pairs: list[tuple[str, str]] = []
    cohorts: dict[str, str] = {}
    backends = ["gymnasium", "envpool"] if HAS_ENVPOOL else ["gymnasium"]
    for task, recipe, counts in (
        ("CartPole", cartpole, cfg.cartpole_envs),
        ("LunarLander", lunarlander, cfg.lunarlander_envs),
    ):
        for n in counts:
            for backend in backends:
                loop = f"{task} x{n} rl_pg training loop ({backend})"
                runs[loop] = recipe_training(recipe, num_envs=n, backend=backend)
                cohorts[loop] = f"{task} x{n}"
                if task == "CartPole":
                    floor = f"{task} x{n} floor: {backend} + MLP, no learning"
                    runs[floor] = cartpole_floor(n, backend)
                else:
                    floor = f"{task} x{n} floor: {backend}, random actions"
                    runs[floor] = random_floor("LunarLander-v3", n, backend)
                pairs.append((loop, floor))
            plain = f"{task} x{n} the same algorithm in plain PyTorch (gymnasium)"
            if "envpool" in backends:  # the other backend's floor, from the default loop
                pairs.append((f"{task} x{n} rl_pg training loop (gymnasium)", floor))
                # Double-buffered: one half of the pool steps while the policy acts on
                # the other (--overlap).
                overlapped = f"{task} x{n} rl_pg training loop (envpool, overlapped)"
                runs[overlapped] = recipe_training(
                    recipe, num_envs=n, backend="envpool", overlap=True
                )
                cohorts[overlapped] = f"{task} x{n}"
                pairs.append((overlapped, f"{task} x{n} rl_pg training loop (envpool)"))
                pairs.append((overlapped, f"{task} x{n} rl_pg training loop (gymnasium)"))
                pairs.append((overlapped, floor))
                pairs.append((overlapped, f"{task} x{n} floor: gymnasium{_floor_kind(task)}"))
                pairs.append((overlapped, plain))
            collected = {
                kind: f"{task} x{n} collection only: {kind} (gymnasium)"
                for kind in ("TorchRL Collector", "SegmentCollector")
            }
            for kind, name in collected.items():
                runs[name] = collection_only(recipe, n, kind)
            pairs.append((collected["SegmentCollector"], collected["TorchRL Collector"]))
            runs[plain] = plain_pytorch_training(recipe, n)
            cohorts[plain] = f"{task} x{n}"
            pairs.append((f"{task} x{n} rl_pg training loop (gymnasium)", plain))
            pairs.append((plain, f"{task} x{n} floor: gymnasium{_floor_kind(task)}"))
            if HAS_TENSORBOARD:  # the plain loop with a CleanRL script's bookkeeping
                kept = f"{task} x{n} the same in plain PyTorch, CleanRL's bookkeeping (gymnasium)"
                runs[kept] = plain_pytorch_training(recipe, n, bookkeeping=True)
                cohorts[kept] = f"{task} x{n}"
                pairs.append((f"{task} x{n} rl_pg training loop (gymnasium)", kept))
                pairs.append((kept, plain))
    if cfg.peers:
        runs["CartPole x1 TorchRL Collector(GymEnv), collection only"] = torchrl_collector
        if importlib.util.find_spec("stable_baselines3") is not None:
            runs["CartPole x8 SB3 A2C training loop"] = sb3_a2c
    return runs, pairs, cohorts


def _floor_kind(task: str) -> str:
    return " + MLP, no learning" if task == "CartPole" else ", random actions"


def main(cfg: Config) -> dict:
    # EnvPool's own API (the raw floors) builds its spaces again at every receive, and
    # gymnasium warns of the same cast each time.
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", BOX_CAST_WARNING, UserWarning)
        return _main(cfg)


def _main(cfg: Config) -> dict:
    torch.set_num_threads(cfg.threads)
    runs, pairs, cohorts = contenders(cfg)
    # Size each contender's repetition to about cfg.seconds from a short probe.
    frames = {
        name: max(cfg.probe_frames, int(run(cfg.probe_frames) * cfg.seconds))
        for name, run in runs.items()
    }
    # A learning loop's speed depends on where its training is (short early episodes
    # reset the environments more often) and on its seed: the loops of one cohort
    # train the same frames (the fewest any was sized to), repetition k from seed k.
    for cohort in set(cohorts.values()):
        members = [name for name, of in cohorts.items() if of == cohort]
        common = min(frames[name] for name in members)
        frames.update(dict.fromkeys(members, common))
    rates: dict[str, list[float]] = {name: [] for name in runs}
    for repetition in range(cfg.repeats):
        for name, run in runs.items():
            seeded = {"seed": repetition} if name in cohorts else {}
            rates[name].append(run(frames[name], **seeded))
    median = {name: statistics.median(r) for name, r in rates.items()}

    print(
        table([[name, rate] for name, rate in median.items()], ["contender", "frames/s (median)"])
    )
    ratios = {f"{loop} / {floor}": median[loop] / median[floor] for loop, floor in pairs}
    intervals = {
        f"{loop} / {floor}": ratio_interval(rates[loop], rates[floor]) for loop, floor in pairs
    }
    print()
    print(
        table(
            [
                [name, ratio, "{:.3g}–{:.3g}".format(*intervals[name])]
                for name, ratio in ratios.items()
            ],
            ["ratio", "x", "90% interval"],
        )
    )
    stock = "CartPole x1 TorchRL Collector(GymEnv), collection only"
    default_loop = f"CartPole x{cartpole.config().num_envs} rl_pg training loop (gymnasium)"
    over_stock = median[default_loop] / median[stock] if stock in median else None
    if over_stock is not None:
        print(f"\nrl_pg CartPole loop / TorchRL stock Collector: {over_stock:.1f}x")
    return write_json(
        cfg.json_path,
        cfg,
        frames_per_repeat=frames,
        frames_per_s=rates,
        median_frames_per_s=median,
        ratios=ratios,
        ratio_intervals=intervals,
        rl_pg_over_stock_collector=over_stock,
    )


if __name__ == "__main__":
    main(tyro.cli(Config))
