"""TorchRL's own ``TestReinforce`` run on ``torchrl.objectives.ReinforceLoss`` and, the
same tests, on ``rl_pg.ReinforceLoss`` substituted for it: the drop-in claim, counted.

The tests come from a checkout (or a bare mirror) of pytorch/rl, at a revision whose
tests the installed TorchRL can run; they are read with ``git archive``, so nothing is
downloaded and the checkout is left as it is. Each class runs in its own pytest process;
the substitution is a pytest plugin (``torchrl_substitute.py``) that swaps the class
before the test module is imported, and stops the run if the module did not get it.

    git clone https://github.com/pytorch/rl /tmp/rl
    python benchmarks/torchrl_compat.py --repo /tmp/rl
"""

from __future__ import annotations

import os
import subprocess
import sys
import tarfile
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import torchrl
import tyro
from common import REPO, table, write_json

HERE = Path(__file__).resolve().parent
TESTS = "test/objectives"


@dataclass
class Config:
    """TorchRL's TestReinforce on TorchRL's ReinforceLoss and on rl_pg's."""

    repo: Path
    """A clone of pytorch/rl (a work tree or a bare repository)."""
    rev: str = "HEAD"
    """The revision whose tests run."""
    selection: str = "test_ppo.py::TestReinforce"
    """The tests, relative to the revision's test/objectives."""
    json_path: Path = REPO / "benchmarks" / "results" / "torchrl_compat.json"
    """Where the results go."""


def counts(junit: Path) -> dict[str, int]:
    """The tests of a JUnit XML report, and how many passed, failed (failures and
    errors) or were skipped."""
    suite = ET.parse(junit).getroot()
    suite = suite if suite.tag == "testsuite" else suite.find("testsuite")
    total, skipped = int(suite.get("tests")), int(suite.get("skipped"))
    failed = int(suite.get("failures")) + int(suite.get("errors"))
    passed = total - failed - skipped
    return {"tests": total, "passed": passed, "failed": failed, "skipped": skipped}


def run_tests(folder: Path, selection: str, *, substitute: bool) -> dict[str, int]:
    """The selected tests' counts, on TorchRL's class or on rl_pg's in its place."""
    junit = folder / ("rl_pg.xml" if substitute else "torchrl.xml")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE), str(folder)]))
    plugin = ["-p", "torchrl_substitute"] if substitute else []
    command = [
        sys.executable, "-m", "pytest", selection, *plugin, "-q", "-p", "no:cacheprovider",
        "-p", "no:randomly", "-p", "no:xdist", f"--junitxml={junit}", "-o", "addopts=",
    ]  # fmt: skip
    done = subprocess.run(command, cwd=folder, env=env, capture_output=True, text=True)
    if not junit.is_file():  # no report: the tests did not even collect
        raise RuntimeError(f"{' '.join(command)} wrote no report:\n{done.stdout}{done.stderr}")
    print(done.stdout.strip().splitlines()[-1])
    return counts(junit)


def main(cfg: Config) -> dict:
    found = subprocess.run(
        ["git", "-C", str(cfg.repo), "rev-parse", "--verify", f"{cfg.rev}^{{commit}}"],
        capture_output=True, text=True,
    )  # fmt: skip
    if found.returncode != 0:
        raise SystemExit(
            f"--repo {cfg.repo} --rev {cfg.rev}: not a git clone of pytorch/rl with that "
            f"revision ({found.stderr.strip()}); clone it: git clone https://github.com/pytorch/rl"
        )
    commit = found.stdout.strip()
    with tempfile.TemporaryDirectory() as tmp:
        archive = Path(tmp) / "tests.tar"
        with archive.open("wb") as out:
            subprocess.run(
                ["git", "-C", str(cfg.repo), "archive", commit, TESTS], stdout=out, check=True
            )
        with tarfile.open(archive) as tar:
            tar.extractall(tmp, filter="data")
        folder = Path(tmp) / TESTS
        results = {
            "torchrl.objectives.ReinforceLoss": run_tests(folder, cfg.selection, substitute=False),
            "rl_pg.ReinforceLoss": run_tests(folder, cfg.selection, substitute=True),
        }
    rows = [[name, *result.values()] for name, result in results.items()]
    print(table(rows, ["class under test", "tests", "passed", "failed", "skipped"]))
    return write_json(
        cfg.json_path, cfg, tests={"repository": "pytorch/rl", "commit": commit},
        torchrl=torchrl.__version__, results=results,
    )  # fmt: skip


if __name__ == "__main__":
    main(tyro.cli(Config))
