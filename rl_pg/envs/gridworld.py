"""The 4x4 gridworld with a goal and a pit, as a batched, torch-native TorchRL environment."""

from __future__ import annotations

from collections import deque

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from rl_pg._checks import check_batch_size, check_bool, check_int, check_real

__all__ = ["GridWorldEnv"]

# up, down, left, right as (row, column) moves
_MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1))


class GridWorldEnv(EnvBase):
    """A ``size x size`` grid with a goal (+1, terminal), a pit (-1, terminal) and walls.

    Actions are up, down, left, right; moving into a wall leaves the agent in place.
    Every other step costs ``step_reward``. Observations are the one-hot of the cell.
    Episodes longer than ``max_steps`` are truncated. All copies in the batch step
    together with a few tensor operations, so large batches are cheap.

    Keyword Args:
        size (int): side of the grid, at least 2. Defaults to ``4``.
        start (tuple of int): (row, column) of the start. Defaults to ``(3, 0)``.
        goal (tuple of int): (row, column) of the goal. Defaults to ``(0, 3)``.
        pit (tuple of int): (row, column) of the pit. Defaults to ``(1, 2)``.
        step_reward (float): reward of every step that does not end in the goal or the
            pit. Defaults to ``-0.1``.
        max_steps (int): truncation horizon. Defaults to ``100``.
        batch_size (int or tuple of int): copies stepped together. Defaults to ``()``.
        device (torch.device, optional): where tensors live. Defaults to ``"cpu"``.
        render (bool): also give the grid as an image under ``"pixels"`` (``uint8``,
            48 pixels a cell: the goal green, the pit red, the agent a blue disc), for
            recordings. Defaults to ``False``.

    Raises:
        ValueError: for cells outside the grid, start/goal/pit that coincide, or
            ``max_steps < 1``.

    Examples:
        >>> import torch
        >>> from rl_pg.envs import GridWorldEnv
        >>> env = GridWorldEnv(batch_size=2)
        >>> round(env.optimal_return, 3)  # 6 moves: 5 steps at -0.1, then the goal
        0.5
        >>> td = env.reset()
        >>> td["action"] = torch.tensor([0, 2])  # up; left into the wall
        >>> out = env.step(td)["next"]
        >>> out["observation"].argmax(-1), out["reward"].squeeze(-1)
        (tensor([ 8, 12]), tensor([-0.1000, -0.1000]))
    """

    batch_locked = True

    def __init__(
        self,
        *,
        size: int = 4,
        start: tuple[int, int] = (3, 0),
        goal: tuple[int, int] = (0, 3),
        pit: tuple[int, int] = (1, 2),
        step_reward: float = -0.1,
        max_steps: int = 100,
        batch_size: int | tuple[int, ...] = (),
        device: torch.device | str | None = "cpu",
        render: bool = False,
    ) -> None:
        size = check_int("size", size, low=2)
        render = check_bool("render", render)
        cells = {}
        for name, cell in (("start", start), ("goal", goal), ("pit", pit)):
            if not hasattr(cell, "__len__") or len(cell) != 2:
                raise ValueError(f"{name} must be a (row, column) pair, got {cell!r}.")
            cell = tuple(check_int(f"{name}[{i}]", c) for i, c in enumerate(cell))
            if not all(0 <= c < size for c in cell):
                raise ValueError(f"{name}={cell!r} is not a cell of a {size}x{size} grid.")
            cells[name] = cell
        start, goal, pit = cells["start"], cells["goal"], cells["pit"]
        if len({start, goal, pit}) != 3:
            raise ValueError(f"start, goal and pit must differ, got {start}, {goal}, {pit}.")
        step_reward = check_real("step_reward", step_reward)
        max_steps = check_int("max_steps", max_steps, low=1)
        batch_size = torch.Size(check_batch_size(batch_size))
        super().__init__(batch_size=batch_size, device=device)
        self.size, self.max_steps = size, max_steps
        self.start, self.goal, self.pit = (r * size + c for r, c in (start, goal, pit))
        n_cells = size * size

        next_cell = torch.empty(n_cells, len(_MOVES), dtype=torch.long)
        for cell in range(n_cells):
            row, col = divmod(cell, size)
            for a, (dr, dc) in enumerate(_MOVES):
                r, c = row + dr, col + dc
                next_cell[cell, a] = r * size + c if 0 <= r < size and 0 <= c < size else cell
        reward = torch.full((n_cells,), float(step_reward))
        reward[self.goal], reward[self.pit] = 1.0, -1.0
        terminal = torch.zeros(n_cells, dtype=torch.bool)
        terminal[[self.goal, self.pit]] = True
        self.register_buffer("next_cell", next_cell.to(self.device))
        self.register_buffer("arrival_reward", reward.to(self.device))
        self.register_buffer("terminal", terminal.to(self.device))
        self.register_buffer("eye", torch.eye(n_cells, device=self.device))
        self.optimal_return = self._optimal_return(float(step_reward))

        # The state (cell, step count) is observed too, so that it travels with the
        # data from one step to the next and the environment itself stays stateless.
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, (*batch_size, n_cells), device=self.device),
            cell=Categorical(n_cells, shape=batch_size, device=self.device),
            step_count=Unbounded(batch_size, dtype=torch.int64, device=self.device),
            shape=batch_size,
        )
        self.render = render
        if render:  # one image per cell the agent can stand on
            frames = _grid_frames(size, self.goal, self.pit)
            self.register_buffer("cell_frames", frames.to(self.device))
            self.observation_spec["pixels"] = Bounded(
                0, 255, (*batch_size, *self.cell_frames.shape[1:]), dtype=torch.uint8,
                device=self.device,
            )  # fmt: skip
        self.action_spec = Categorical(len(_MOVES), shape=batch_size, device=self.device)
        self.reward_spec = Unbounded((*batch_size, 1), device=self.device)
        self.done_spec = Composite(
            {
                key: Categorical(2, (*batch_size, 1), dtype=torch.bool, device=self.device)
                for key in ("done", "terminated", "truncated")
            },
            shape=batch_size,
        )

    def _optimal_return(self, step_reward: float) -> float:
        """Return of the shortest path from start to goal that avoids the pit.

        One cell cannot disconnect a grid, so the breadth-first search always gets there.
        """
        moves = {self.start: 0}
        queue = deque([self.start])
        while self.goal not in moves:
            cell = queue.popleft()
            for nxt in self.next_cell[cell].tolist():
                if nxt not in moves and nxt != self.pit:
                    moves[nxt] = moves[cell] + 1
                    queue.append(nxt)
        return step_reward * (moves[self.goal] - 1) + 1.0

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        shape = self.batch_size
        cell = torch.full(shape, self.start, dtype=torch.long, device=self.device)
        return TensorDict(
            {
                "observation": self.eye[cell],
                "cell": cell,
                "step_count": torch.zeros(shape, dtype=torch.long, device=self.device),
                **self.full_done_spec.zero(),
                **self._pixels(cell),
            },
            batch_size=shape,
            device=self.device,
        )

    def _pixels(self, cell: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"pixels": self.cell_frames[cell]} if self.render else {}

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        cell = self.next_cell[tensordict["cell"], tensordict["action"]]
        step_count = tensordict["step_count"] + 1
        terminated = self.terminal[cell].unsqueeze(-1)
        truncated = (step_count >= self.max_steps).unsqueeze(-1) & ~terminated
        return TensorDict(
            {
                "observation": self.eye[cell],
                "cell": cell,
                "step_count": step_count,
                "reward": self.arrival_reward[cell].unsqueeze(-1),
                "done": terminated | truncated,
                "terminated": terminated,
                "truncated": truncated,
                **self._pixels(cell),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _set_seed(self, seed: int | None) -> None:
        """The gridworld is deterministic: seeding has nothing to do."""


_CELL = 48  # pixels a side
_FLOOR, _LINE, _GOAL, _PIT, _AGENT = (236, 236, 228), (190, 190, 190), (70, 170, 90), (
    200, 70, 60), (50, 100, 220)  # fmt: skip


def _grid_frames(size: int, goal: int, pit: int) -> torch.Tensor:
    """``[size * size, H, W, 3]`` uint8: the grid with the agent on each cell."""
    side = size * _CELL
    grid = torch.tensor(_FLOOR, dtype=torch.uint8).expand(side, side, 3).clone()
    for cell, colour in ((goal, _GOAL), (pit, _PIT)):
        row, col = divmod(cell, size)
        square = (slice(row * _CELL, (row + 1) * _CELL), slice(col * _CELL, (col + 1) * _CELL))
        grid[square] = torch.tensor(colour, dtype=torch.uint8)
    lines = torch.arange(side) % _CELL == 0
    grid[lines, :] = grid[:, lines] = torch.tensor(_LINE, dtype=torch.uint8)
    grid[-1, :] = grid[:, -1] = torch.tensor(_LINE, dtype=torch.uint8)
    y, x = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    frames = grid.expand(size * size, side, side, 3).clone()
    for cell in range(size * size):
        row, col = divmod(cell, size)
        centre_y, centre_x = (row + 0.5) * _CELL, (col + 0.5) * _CELL
        disc = (y + 0.5 - centre_y) ** 2 + (x + 0.5 - centre_x) ** 2 <= (0.3 * _CELL) ** 2
        frames[cell][disc] = torch.tensor(_AGENT, dtype=torch.uint8)
    return frames
