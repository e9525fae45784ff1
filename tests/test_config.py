"""TrainConfig: recipes change defaults in the class statement, and every recipe does."""

from __future__ import annotations

import ast
import dataclasses
import inspect
from dataclasses import dataclass

import pytest
import tyro

from rl_pg.recipes import NAMES, load
from rl_pg.training import Count, TrainConfig


@dataclass
class _Recipe(TrainConfig, lr=5e-3, gamma=0.5, max_grad_norm=1.0):
    """A recipe's config."""

    hidden: Count = 3
    """Width."""


class TestDefaultsInTheClassStatement:
    def test_new_defaults_keep_the_fields_order_type_and_help(self):
        cfg = _Recipe()
        assert (cfg.lr, cfg.gamma, cfg.max_grad_norm, cfg.hidden) == (5e-3, 0.5, 1.0, 3)
        base = [f.name for f in dataclasses.fields(TrainConfig)]
        assert [f.name for f in dataclasses.fields(_Recipe)] == [*base, "hidden"]
        assert TrainConfig().lr == 1e-3  # the base is untouched

    def test_bounds_still_hold(self):
        with pytest.raises(ValueError, match=r"gamma \(--gamma\) must be a finite number"):
            _Recipe(gamma=2.0)
        with pytest.raises(ValueError, match=r"max_grad_norm .* must be a finite number > 0"):
            _Recipe(max_grad_norm=-1.0)

    def test_help_shows_the_new_default_with_the_base_text(self, capsys):
        with pytest.raises(SystemExit):
            tyro.cli(_Recipe, args=["--help"])
        out = " ".join(capsys.readouterr().out.split())
        assert "Discount factor. (default: 0.5)" in out.replace("│", "").replace("  ", " ")

    def test_an_unknown_field_is_refused(self):
        with pytest.raises(TypeError, match="sets defaults of lrr, which TrainConfig"):

            @dataclass
            class _Typo(TrainConfig, lrr=1.0):
                pass

    def test_declaring_and_overriding_the_same_field_is_refused(self):
        with pytest.raises(TypeError, match="both declares and overrides lr"):

            @dataclass
            class _Both(TrainConfig, lr=1.0):
                lr: float = 2.0


@pytest.mark.parametrize("name", NAMES)
def test_recipes_declare_only_the_fields_they_add(name):
    config = load(name).config
    body = ast.parse(inspect.getsource(config)).body[0].body
    declared = {node.target.id for node in body if isinstance(node, ast.AnnAssign)}
    assert not declared & {f.name for f in dataclasses.fields(TrainConfig)}


def test_the_fields_that_act_only_with_another_name_real_fields_and_values():
    # A renamed field or value would leave a flag that does nothing labelled as a setting.
    import typing

    hints = typing.get_type_hints(TrainConfig, include_extras=True)
    names = {field.name for field in dataclasses.fields(TrainConfig)}
    for name, (other, values) in TrainConfig.acts_only_with.items():
        assert name in names and other in names, (name, other)
        if values != "not None":
            assert set(values) <= set(typing.get_args(hints[other])), (other, values)


def test_a_resume_refuses_every_change_to_what_the_run_learns_from():
    """Only where and how the run goes on may change on resume: no field of the returns,
    the loss, the optimiser or the evaluations, and each other field's change is named."""
    from rl_pg.training.config import RESUMABLE_FIELDS, config_dict
    from rl_pg.training.resuming import changed_settings

    learning = {
        name for group in ("returns", "loss", "optimiser", "evaluation")
        for name in TrainConfig.groups[group][1]
    }  # fmt: skip
    assert "gamma" in learning and not learning & RESUMABLE_FIELDS
    for name in NAMES:
        cfg = load(name).config(**({"env_id": "Acrobot-v1"} if name == "gym" else {}))
        stored = config_dict(cfg)
        for field in stored.keys() - RESUMABLE_FIELDS:
            changed = changed_settings(cfg, {**stored, field: "another value"})
            assert changed == {field: ("another value", stored[field])}, (name, field)
