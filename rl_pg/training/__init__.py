"""The harness that runs experiments on top of rl_pg's components.

One file per concern, imports pointing down (config first, loop and cli last):

* [`settings`][rl_pg.training.settings] and [`learning`][rl_pg.training.learning]: the
  config's groups, each with the rules among its fields; every part below takes the
  groups it acts on;
* [`config`][rl_pg.training.config]: ``TrainConfig``, every group at once, and the
  rules across groups;
* [`collection`][rl_pg.training.collection]: the collector and every decision that
  depends on local, multi-process or Ray collection;
* [`workers`][rl_pg.training.workers] and [`cluster`][rl_pg.training.cluster]: worker
  processes or Ray actors kept running (lost and hung ones replaced), and their Ray;
* [`optimisation`][rl_pg.training.optimisation]: the loss, the optimiser, one update;
* [`metrics`][rl_pg.training.metrics]: training-episode returns;
* [`loggers`][rl_pg.training.loggers]: CSV, TensorBoard, W&B and MLflow;
* [`console`][rl_pg.training.console]: the progress shown while training, the summary;
* [`checkpoints`][rl_pg.training.checkpoints]: what a checkpoint holds, resuming and
  deploying from one;
* [`run_dir`][rl_pg.training.run_dir]: the run directory, its lock, its config and the
  summary;
* [`provenance`][rl_pg.training.provenance]: the code, libraries and machine each
  session of a run ran on;
* [`interrupt`][rl_pg.training.interrupt]: Ctrl-C;
* [`callbacks`][rl_pg.training.callbacks]: behaviours plugged into the loop (yours;
  early stop, kept checkpoints and the gradient-noise measurement);
* [`metric`][rl_pg.training.metric]: the evaluation entry a run is judged by
  (``--select-by``) and which way is better;
* [`selection`][rl_pg.training.selection]: which policy is evaluated and kept as
  ``best.pt`` (evaluations, the policy average, confirmation replays);
* [`run`][rl_pg.training.run]: the pieces of one run, which callbacks receive;
* [`loop`][rl_pg.training.loop]: ``train()``;
* [`recipe`][rl_pg.training.recipe]: ``Recipe``, what a recipe gives ``train``,
  ``rl-pg`` and ``play``;
* [`resuming`][rl_pg.training.resuming]: what a resumed run may change;
* [`comparison`][rl_pg.training.comparison]: several variants and seeds;
* [`tuning`][rl_pg.training.tuning] over [`studies`][rl_pg.training.studies]: Optuna
  searches;
* [`curves`][rl_pg.training.curves]: every plot, drawn from the CSV logs, over
  [`aggregates`][rl_pg.training.aggregates] (statistics over seeds).

The library (losses, estimators, transforms, environments, models) knows nothing of
this package.
"""

from rl_pg._checks import check_fields
from rl_pg.training.callbacks import Callback
from rl_pg.training.checkpoints import load_models, read_run
from rl_pg.training.config import Count, NonNegative, Positive, Range, TrainConfig
from rl_pg.training.loggers import scalar_log_rows
from rl_pg.training.loop import train
from rl_pg.training.metric import Metric
from rl_pg.training.optimisation import TrainingDiverged
from rl_pg.training.recipe import Recipe
from rl_pg.training.run_dir import RunDirBusy, RunDirectory, RunDirUnusable

__all__ = [
    "Callback",
    "Count",
    "Metric",
    "NonNegative",
    "Positive",
    "Range",
    "Recipe",
    "RunDirBusy",
    "RunDirUnusable",
    "RunDirectory",
    "TrainConfig",
    "TrainingDiverged",
    "check_fields",
    "load_models",
    "read_run",
    "scalar_log_rows",
    "train",
]
