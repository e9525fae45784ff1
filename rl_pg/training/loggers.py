"""Where a run's scalars go: TorchRL's CSV logger always (the learning curves are read
from it), TensorBoard, Weights & Biases and MLflow when the config asks."""

from __future__ import annotations

import hashlib
import os
import re
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from torchrl.record.loggers import (
    CSVLogger,
    Logger,
    MLFlowLogger,
    TensorboardLogger,
    WandbLogger,
)
from torchrl.record.loggers.csv import CSVExperiment

from rl_pg._checks import require_extra
from rl_pg.checkpoint import write_atomically
from rl_pg.training.settings import LoggingSettings

__all__ = [
    "VIEWER_SHARE",
    "BufferedCSVLogger",
    "BufferedMLFlowLogger",
    "Loggers",
    "scalar_log_rows",
]


VIEWER_SHARE = 0.05
"""The share of a run's time a viewer's logging backend may take for the training
scalars (see [`Loggers.log_metrics`][rl_pg.training.loggers.Loggers.log_metrics])."""


class Loggers:
    """Sends each scalar to every TorchRL logger of the run.

    The CSV logger always writes ``logs/csv`` (the learning curve is read from it);
    TensorBoard, Weights & Biases and MLflow are added when the config asks, and every
    logger receives the run's hyper-parameters first.

    Args:
        settings (LoggingSettings): the run's logging group: which loggers, and where.
        run_dir (Path): the run directory.
        name (str): the recipe's name (MLflow's experiment).

    Keyword Args:
        hparams (dict): the hyper-parameters every logger receives first (the run's
            config, as ``config.json`` holds it).
        resume_at (int, optional): frames of the checkpoint a resumed run starts from;
            CSV rows logged after it by the killed run are dropped first (they are
            redone). The other loggers keep them: their viewers show both.

    Raises:
        ImportError: a logger's package is missing; the message names the extra.
    """

    def __init__(
        self,
        settings: LoggingSettings,
        run_dir: Path,
        name: str,
        *,
        hparams: dict[str, Any],
        resume_at: int | None,
    ) -> None:
        for wanted, module, extra in (
            (settings.tensorboard, "tensorboard", "tensorboard"),
            (settings.wandb, "wandb", "wandb"),
            (settings.mlflow, "mlflow", "mlflow"),
        ):
            if wanted:
                require_extra(module, extra, f"--{extra}")
        log_dir = run_dir / "logs"
        if resume_at is not None:
            _trim_csv_logs(log_dir, resume_at)
        self.csv = BufferedCSVLogger(exp_name="csv", log_dir=str(log_dir))
        self.loggers: list[Logger] = [self.csv]
        if settings.tensorboard:
            self.loggers.append(TensorboardLogger(exp_name="tensorboard", log_dir=str(log_dir)))
        if settings.wandb:
            self.loggers.append(_wandb(settings, run_dir))
        if settings.mlflow:
            self.loggers.append(_mlflow(settings, run_dir, name))
        # Loggers take scalars (TensorBoard's hparams refuses a list): a pair is shown whole.
        hyperparameters = {
            key: value if isinstance(value, int | float | str | bool) else str(value)
            for key, value in hparams.items()
            if value is not None
        }
        for logger in self.loggers:
            logger.log_hparams(hyperparameters)
        self._started = time.perf_counter()
        self._spent: dict[int, float] = {}  # seconds each viewer's backend took, by id

    def log_scalar(self, name: str, value: float, step: int) -> None:
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)

    def log_metrics(self, metrics: dict[str, float], step: int) -> None:
        """Logs an update's scalars together: one call per backend (W&B writes them as
        one row, at a seventh of the cost of one call per scalar). The CSV logs get
        every update's; a viewer's backend (TensorBoard, W&B, MLflow) gets an update's
        unless it has used more than ``VIEWER_SHARE`` of the time since the run
        started, so that no backend slows the training by more than that share (a
        cheap one gets every update, an expensive one fewer points of the same curves;
        the evaluations always reach every backend)."""
        now = time.perf_counter()
        elapsed = now - self._started
        for logger in self.loggers:
            if logger is not self.csv:
                spent = self._spent.get(id(logger), 0.0)
                if spent > VIEWER_SHARE * elapsed:
                    continue
            start = time.perf_counter()
            logger.log_metrics(metrics, step=step)
            if logger is not self.csv:
                self._spent[id(logger)] = spent + time.perf_counter() - start

    def flush(self) -> None:
        """Writes the CSV rows and MLflow metrics held back (the loop calls it before
        each evaluation and checkpoint, and at the end)."""
        for logger in self.loggers:
            if isinstance(logger, BufferedCSVLogger | BufferedMLFlowLogger):
                logger.flush()

    def close(self) -> None:
        """Writes what is held back and ends the W&B and MLflow runs (their files are
        complete afterwards)."""
        self.flush()
        for logger in self.loggers:
            if isinstance(logger, BufferedMLFlowLogger):
                logger.wait()
            if isinstance(logger, WandbLogger):
                logger.experiment.finish()
            elif isinstance(logger, MLFlowLogger):
                import mlflow

                mlflow.end_run()


class _BufferedCSVExperiment(CSVExperiment):
    """TorchRL's CSV experiment, its rows written to the files in bulk: at most
    ``flush_every`` seconds after they are logged, or at ``flush()``, where TorchRL's
    own checks that the file exists and flushes it for every scalar."""

    def __init__(self, log_dir: str, *, flush_every: float, **kwargs) -> None:
        super().__init__(log_dir, **kwargs)
        self.flush_every = flush_every
        self.due = time.monotonic() + flush_every
        self._by_name: dict[str, object] = {}

    def add_scalar(self, name: str, value: float, global_step: int | None = None) -> None:
        if global_step is None:
            global_step = len(self.scalars[name])
        value = float(value)
        self.scalars[name].append((global_step, value))
        file = self._by_name.get(name)  # no path built per row: a third of its cost
        if file is None:
            path = os.path.join(self.log_dir, "scalars", name + ".csv")
            file = self.files.get(path)
            if file is None:
                os.makedirs(os.path.dirname(path), exist_ok=True)
                file = self.files[path] = open(path, "a+")  # noqa: SIM115 (kept open, as TorchRL)
            self._by_name[name] = file
        file.write(f"{global_step},{value}\n")  # TorchRL's row: step and str(float)
        if time.monotonic() >= self.due:
            self.flush()

    def flush(self) -> None:
        for file in self.files.values():
            file.flush()
        self.due = time.monotonic() + self.flush_every


class BufferedCSVLogger(CSVLogger):
    """TorchRL's [`CSVLogger`](https://docs.pytorch.org/rl/stable/reference/generated/torchrl.record.loggers.csv.CSVLogger.html)
    (same files, same rows) whose scalar rows reach their files at least every
    ``flush_every`` seconds and at every ``flush()``, instead of one write to disk per
    scalar. Rows logged since the last flush are lost if the process is killed: the
    training loop flushes before each checkpoint, so a resumed run loses none it keeps.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from rl_pg.training.loggers import BufferedCSVLogger
        >>> log_dir = tempfile.mkdtemp()
        >>> logger = BufferedCSVLogger("csv", log_dir, flush_every=60.0)
        >>> logger.log_scalar("loss/actor", 0.5, step=128)
        >>> logger.flush()
        >>> (Path(log_dir) / "csv/scalars/loss/actor.csv").read_text()
        '128,0.5\\n'
    """

    def __init__(self, exp_name: str, log_dir: str, *, flush_every: float = 1.0) -> None:
        if isinstance(flush_every, bool) or not isinstance(flush_every, (int, float)):
            raise TypeError(f"flush_every must be a number of seconds, got {flush_every!r}.")
        if not flush_every >= 0:  # NaN too
            raise ValueError(
                f"flush_every must be >= 0 seconds (0 writes every row at once), got {flush_every}."
            )
        self.flush_every = flush_every
        super().__init__(exp_name=exp_name, log_dir=log_dir)

    def _create_experiment(self) -> _BufferedCSVExperiment:
        return _BufferedCSVExperiment(
            os.path.join(self.log_dir, self.exp_name),
            video_format=self.video_format,
            video_fps=self.video_fps,
            flush_every=self.flush_every,
        )

    def flush(self) -> None:
        """Writes the rows held back to their files."""
        self.experiment.flush()


def _wandb(settings: LoggingSettings, run_dir: Path) -> Logger:
    os.environ.setdefault("WANDB_SILENT", "true")  # the console is rl_pg's
    path = str(run_dir.resolve())
    # The same W&B run id for the run directory: a resumed run continues its W&B run.
    run_id = f"{run_dir.name[:48]}-{hashlib.sha1(path.encode()).hexdigest()[:8]}"
    return WandbLogger(
        exp_name=run_dir.name,
        offline=settings.wandb_mode == "offline",
        save_dir=path,
        project=settings.wandb_project,
        id=re.sub(r"[^A-Za-z0-9_-]", "-", run_id),
        resume="allow",
    )


class BufferedMLFlowLogger(MLFlowLogger):
    """TorchRL's [`MLFlowLogger`](https://docs.pytorch.org/rl/stable/reference/generated/torchrl.record.loggers.MLFlowLogger.html)
    (same experiment, run and metrics) whose scalars reach the tracking store in
    batches, one ``log_batch`` call at least every ``flush_every`` seconds and at every
    ``flush()``, handed to MLflow's asynchronous logging, instead of two synchronous
    calls to the store per scalar (TorchRL's sets the experiment and logs the metric
    each time). Each metric keeps the time it was logged at; ``wait()`` returns once
    the store holds them all (the run's end calls it).
    """

    def __init__(self, exp_name: str, tracking_uri: str, *, flush_every: float = 5.0) -> None:
        super().__init__(exp_name=exp_name, tracking_uri=tracking_uri)
        from mlflow.tracking import MlflowClient

        self.flush_every = flush_every
        self._client = MlflowClient(tracking_uri)
        self._run_id = self.experiment.info.run_id
        self._pending: list = []
        self._operations: list = []  # MLflow's futures of the batches handed over
        self._due = time.monotonic() + flush_every

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        from mlflow.entities import Metric

        self._pending.append(Metric(name, float(value), int(time.time() * 1000), step or 0))
        if time.monotonic() >= self._due:
            self.flush()

    def log_metrics(self, metrics: dict[str, Any], step: int | None = None, **kwargs) -> Any:
        """Each scalar held back as ``log_scalar`` holds it (TorchRL's sends them to the
        store at once, one synchronous call per update)."""
        return Logger.log_metrics(self, metrics, step, **kwargs)

    def flush(self) -> None:
        """Hands the metrics held back to MLflow's asynchronous logging (1 000 a batch,
        MLflow's limit), which writes them to the store on a thread of its own."""
        for start in range(0, len(self._pending), 1000):
            batch = self._pending[start : start + 1000]
            self._operations.append(
                self._client.log_batch(self._run_id, metrics=batch, synchronous=False)
            )
        self._pending.clear()
        self._due = time.monotonic() + self.flush_every

    def wait(self) -> None:
        """Flushes, then waits until the store holds every metric logged (at the end)."""
        self.flush()
        for operation in self._operations:
            operation.wait()
        self._operations.clear()


def _mlflow(settings: LoggingSettings, run_dir: Path, name: str) -> Logger:
    import mlflow

    uri = settings.mlflow_uri or mlflow.get_tracking_uri()
    _check_tracking_server(uri)
    logger = BufferedMLFlowLogger(exp_name=name, tracking_uri=uri)  # starts an MLflow run
    mlflow.set_tags({"mlflow.runName": run_dir.name, "run_dir": str(run_dir.resolve())})
    return logger


def _check_tracking_server(uri: str, timeout: float = 5.0) -> None:
    """Fails at once, naming ``uri``, when no server answers an http(s) tracking URI
    (MLflow itself retries for minutes, silently, before it gives up).

    Raises:
        ConnectionError: nothing answered within ``timeout`` seconds.
    """
    if not uri.startswith(("http://", "https://")):
        return  # a file or database store: MLflow opens it itself, and says what is wrong
    try:
        with urllib.request.urlopen(uri.rstrip("/") + "/health", timeout=timeout):
            pass
    except urllib.error.HTTPError:
        return  # a server answered (a proxy may refuse /health): MLflow takes it from here
    except (OSError, ValueError) as err:  # refused, unknown host, timed out, bad URL
        reason = getattr(err, "reason", err)
        raise ConnectionError(
            f"No MLflow server answers at --mlflow-uri {uri} ({reason}). Start one there "
            f"(mlflow server --host HOST --port PORT), correct the URI, or log to a local "
            f"store instead: --mlflow-uri sqlite:///mlflow.db."
        ) from err


def _trim_csv_logs(log_dir: Path, frames: int) -> None:
    """Drops the rows a killed run logged after its last checkpoint (they are redone).

    Each file is replaced atomically: a run killed while trimming leaves the file as
    it was, and the next resume trims it again. A row cut short by the kill (no
    newline, or not two numbers) is dropped with the rest.
    """
    for path in log_dir.glob("csv/scalars/**/*.csv"):
        text = path.read_text()
        rows = text.split("\n")[:-1]  # what follows the last newline is a torn row
        kept = [row for row in rows if (parsed := _parse_row(row)) and parsed[0] <= frames]
        if len(kept) != len(rows) or not text.endswith("\n"):
            write_atomically(path, "".join(f"{row}\n" for row in kept))


def scalar_log_rows(text: str) -> list[tuple[float, float]]:
    """The complete ``step,value`` rows of a CSV scalar log.

    What follows the last newline, or a row that is not two numbers, was cut short by
    a killed run and is left out.

    Examples:
        >>> from rl_pg.training import scalar_log_rows
        >>> scalar_log_rows("64,0.5\\n128,0.75\\n19")
        [(64.0, 0.5), (128.0, 0.75)]
    """
    return [parsed for row in text.split("\n")[:-1] if (parsed := _parse_row(row))]


def _parse_row(row: str) -> tuple[float, float] | None:
    fields = row.split(",")
    if len(fields) != 2:
        return None
    try:
        return float(fields[0]), float(fields[1])
    except ValueError:
        return None
