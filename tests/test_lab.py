"""rl_pg.app.lab and ``rl-pg lab variance``: seeds trained with the
gradient statistics, then a figure and a table drawn from their logs alone."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np
import pytest
from test_cli import in_process

from rl_pg.app.lab import _markdown
from rl_pg.app.noise import noise_scale_curve

QUICK = ["--total-updates", "4", "--episodes-per-batch", "6"]
RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


class TestNoiseScaleCurve:
    def test_pools_every_run_of_a_window(self):
        # B = mean trace / mean signal over all the runs' measurements in the window.
        a = {"frames": np.array([10.0, 20.0]), "trace_covariance": np.array([2.0, 6.0]),
             "grad_norm_sq": np.array([1.0, 3.0]), "units": np.array([4.0, 4.0])}  # fmt: skip
        b = {"frames": np.array([15.0]), "trace_covariance": np.array([10.0]),
             "grad_norm_sq": np.array([-1.0]), "units": np.array([10.0])}  # fmt: skip
        frames, scale, snr = noise_scale_curve([a, b], np.array([0.0, 30.0]))
        assert frames.tolist() == [15.0]
        assert scale[0] == pytest.approx((18 / 3) / (3 / 3))
        assert snr[0] == pytest.approx(6 / scale[0])

    def test_an_empty_window_has_no_noise_scale(self):
        run = {"frames": np.array([5.0]), "trace_covariance": np.array([1.0]),
               "grad_norm_sq": np.array([1.0]), "units": np.array([2.0])}  # fmt: skip
        _, scale, _ = noise_scale_curve([run], np.array([0.0, 10.0, 20.0]))
        assert scale[0] == 1.0 and np.isnan(scale[1])


class TestLabCommand:
    def test_trains_the_seeds_then_writes_the_figure_and_the_table(self, tmp_path, capsys):
        root = tmp_path / "lab"
        args = ["lab", "variance", "gridworld", "--seeds", "0", "1", "--every", "1"]
        status, out, err = in_process(*args, "--run-dir", str(root), *QUICK, capsys=capsys)
        assert status == 0, err
        assert out.startswith("| estimator | tr Σ / tr Σ of R(τ) | noise scale B |")
        table = json.loads((root / "variance.json").read_text())
        assert table["seeds"] == [0, 1]
        assert "reward_to_go_minus_value" in table["estimators"]
        assert all(row["measurements"] == 8 for row in table["estimators"].values())
        assert (root / "variance.png").read_bytes()[:4] == b"\x89PNG"
        assert (root / "variance_by_seed.png").read_bytes()[:4] == b"\x89PNG"
        assert table["held"] == {"0": None, "1": None}  # no rl-pg evaluate yet
        # A second call keeps the finished seeds (no new training) and redraws.
        before = (root / "seed0" / "checkpoint.pt").stat().st_mtime_ns
        status, out, err = in_process(*args, "--run-dir", str(root), *QUICK, capsys=capsys)
        assert status == 0, err
        assert (root / "seed0" / "checkpoint.pt").stat().st_mtime_ns == before
        # Once evaluated both ways, a seed is labelled by whether its best checkpoint holds.
        for mode in ("greedy", "sampled"):
            status, _, err = in_process(
                "evaluate", str(root / "seed0"), "--episodes", "2",
                *(["--sample"] if mode == "sampled" else []), capsys=capsys,
            )  # fmt: skip
            assert status == 0, err
        status, _, err = in_process(*args, "--run-dir", str(root), *QUICK, capsys=capsys)
        held = json.loads((root / "variance.json").read_text())["held"]
        assert set(held["0"]) == {"holds", "greedy", "sampled"} and held["1"] is None

    def test_runs_in_groups_are_measured_and_tabulated_by_group(self, tmp_path, capsys):
        root = tmp_path / "lab"
        args = ["lab", "variance", "gridworld", "--seeds", "0", "1", "--every", "1"]
        grouped = ["--baseline", "leave_one_out", "--batch-mode", "episodes", "--group-size", "3",
                   "--num-envs", "6"]  # fmt: skip
        status, out, err = in_process(
            *args, "--run-dir", str(root), *QUICK, *grouped, capsys=capsys
        )
        assert status == 0, err
        assert "| noise scale B (groups of 3) |" in out.splitlines()[0]
        table = json.loads((root / "variance.json").read_text())
        assert (table["unit"], table["group_size"]) == ("group", 3)
        for name in ("loss", "reward_to_go", "leave_one_out", "group_mean", "group_mean_scaled"):
            assert table["estimators"][name]["units"] == 2, name  # 6 episodes, 2 groups
        leave_one_out = table["estimators"]["leave_one_out"]
        assert leave_one_out["variance_relative_to_episode_return"] > 0

    def test_one_environment_plays_its_groups_in_rounds(self, tmp_path, capsys):
        # A simulator with one engine per process (MetaDrive) plays a group's episodes
        # one after another from one seed: the lab measures them by group as well.
        root = tmp_path / "lab"
        grouped = ["--baseline", "leave_one_out", "--batch-mode", "episodes", "--group-size", "3",
                   "--num-envs", "1"]  # fmt: skip
        status, _, err = in_process(
            "lab", "variance", "gridworld", "--seeds", "0", "--every", "1", "--run-dir",
            str(root), *QUICK, *grouped, capsys=capsys,
        )  # fmt: skip
        assert status == 0, err
        table = json.loads((root / "variance.json").read_text())
        assert (table["unit"], table["group_size"]) == ("group", 3)
        assert table["estimators"]["leave_one_out"]["units"] == 2  # 6 episodes, 2 groups
        assert (root / "variance_by_seed.png").read_bytes()[:4] == b"\x89PNG"

    @pytest.mark.parametrize(
        ("values", "scale"),
        [([[0.5, -1.0, np.nan]], "log"), ([[-1.0, 0.0], [np.nan]], "linear"), ([], "linear")],
    )
    def test_a_panel_without_positive_values_stays_linear(self, values, scale):
        # A noise scale estimated on few batches can be <= 0; a log axis of nothing
        # positive fails in matplotlib, so the panel stays linear and says so.
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from rl_pg.app.lab_figures import log_scale

        figure, ax = plt.subplots()
        for line in values:
            ax.plot(range(len(line)), line)
        log_scale(ax, "noise scale B")
        assert ax.get_yscale() == scale
        assert ("none > 0" in ax.get_ylabel()) == (scale == "linear")
        figure.savefig(io.BytesIO(), format="png")  # draws: no error either way
        plt.close(figure)

    @pytest.mark.parametrize(
        ("flags", "match"),
        [(["--seeds"], "at least one seed"), (["--every", "0"], "positive number of updates")],
    )
    def test_rejects(self, tmp_path, capsys, flags, match):
        status, _, err = in_process(
            "lab", "variance", "gridworld", *flags, "--run-dir", str(tmp_path), capsys=capsys
        )
        assert status != 0 and match in err

    def test_a_folder_of_another_setting_is_refused_before_any_training(self, tmp_path, capsys):
        root = tmp_path / "lab"
        args = ["lab", "variance", "gridworld", "--seeds", "0", "--every", "1", "--run-dir",
                str(root), *QUICK]  # fmt: skip
        assert in_process(*args, capsys=capsys)[0] == 0
        status, _, err = in_process(*args[:-len(QUICK)], "--seeds", "0", "1", *QUICK, "--lr",
                                    "0.5", capsys=capsys)  # fmt: skip
        assert status == 1 and re.search(r"seed0 was trained with --lr [\d.]+ \(now 0.5\):", err)
        assert err.count("\n") == 1 and not (root / "seed1").exists()

    def test_runs_too_short_to_be_measured_say_what_to_change(self, tmp_path, capsys):
        status, _, err = in_process(
            "lab", "variance", "gridworld", "--seeds", "0", "--every", "1000", "--run-dir",
            str(tmp_path / "lab"), *QUICK, capsys=capsys,
        )  # fmt: skip
        assert status == 1 and re.search(r"measured nothing: seed 0 trained \d+ updates", err)
        assert "Lower --every" in err

    def test_runs_without_statistics_are_refused(self, tmp_path, capsys):
        root = tmp_path / "lab"
        status, _, err = in_process(
            "train", "gridworld", "--run-dir", str(root / "seed0"), *QUICK, capsys=capsys
        )
        assert status == 0, err
        status, _, err = in_process(
            "lab", "variance", "gridworld", "--seeds", "0", "--run-dir", str(root), *QUICK,
            capsys=capsys,
        )  # fmt: skip
        assert status != 0 and "trained without --grad-stats, not by rl-pg lab" in err


@pytest.mark.parametrize("stored", sorted(RESULTS.glob("variance_*.json")), ids=lambda p: p.stem)
def test_the_documented_tables_are_the_stored_results(stored):
    # The docs include docs/results/variance_<recipe>.md; it must be what the lab
    # writes from the stored variance_<recipe>.json, never a table edited by hand.
    assert stored.with_suffix(".md").read_text() == _markdown(json.loads(stored.read_text()))
