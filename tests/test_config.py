"""config.toml: the shipped file is complete and loads to the defaults; bad keys and values are named."""

from __future__ import annotations

import tomllib
from dataclasses import fields, replace
from pathlib import Path

import pytest

from mocapd.core.loss import CauchyLoss, HuberLoss
from mocapd.core.solver import TERM_NAMES, LMOptions
from mocapd.core.terms import CostOptions
from mocapd.errors import ConfigError
from mocapd.service.config import DEFAULT_CONFIG, load_config, parse_config


def test_shipped_config_equals_the_defaults() -> None:
    """The seed's weights everywhere but λ_R and λ_A, which the development split re-tuned (docs/accuracy.md)."""
    cfg = load_config()
    assert cfg.solver.cost == replace(CostOptions.seed_003(), lambda_orientation=100.0, lambda_acceleration=1e-4)
    assert cfg.solver.lm.options() == LMOptions()
    assert cfg.solver.backend == "compiled"


def test_library_defaults_are_the_shipped_config() -> None:
    """One source of truth (issue 14): a PoseSolver built with no options solves the daemon's problem. Before,
    ``CostOptions()`` had the seed's λ_R = 1 against the shipped 100 (18-20° knee error instead of 4-6°)."""
    from mocapd.core.skeleton import Skeleton
    from mocapd.core.solver import PoseSolver

    shipped = load_config().solver
    assert CostOptions() == shipped.cost
    assert CostOptions().lambda_orientation == 100.0
    solver = PoseSolver(Skeleton.from_height(1.75))
    assert solver.cost_options == shipped.cost and solver.lm == shipped.lm.options()


def test_shipped_config_documents_every_solver_option() -> None:
    data = tomllib.loads(DEFAULT_CONFIG.read_text(encoding="utf-8"))
    solver = data["solver"]
    assert set(solver["lm"]) == {f.name for f in fields(LMOptions)}
    assert set(solver["terms"]) == set(TERM_NAMES)
    for term in TERM_NAMES:
        assert {"enabled", "weight", "loss"} <= set(solver["terms"][term])
    for key, line in (
        (k, ln)
        for ln in DEFAULT_CONFIG.read_text(encoding="utf-8").splitlines()
        for k in solver["lm"]
        if ln.startswith(f"{k} =")
    ):
        assert "#" in line, f"solver.lm.{key} has no comment"


def test_overrides_are_applied(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text(
        '[solver]\nbackend = "numpy"\n[solver.terms.position]\nweight = 2e-3\nloss = "huber"\nloss_scale = 3.0\n'
        "[solver.terms.floor]\nenabled = false\n[solver.lm]\nmax_iterations = 7\n",
        encoding="utf-8",
    )
    cfg = load_config(p)
    assert cfg.solver.backend == "numpy"
    assert cfg.solver.cost.lambda_position == 2e-3
    assert cfg.solver.cost.loss_position == HuberLoss(3.0)
    assert cfg.solver.cost.loss_acceleration == CauchyLoss(1.0)
    assert cfg.solver.cost.use_floor is False
    assert cfg.solver.lm.max_iterations == 7


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (
            {"solvr": {}},
            r"^unknown section solvr; allowed: calibration, cameras, daemon, detector, fusion, imu, record, solver, "
            r"synthetic",
        ),
        ({"solver": {"backend": "gpu"}}, r"solver.backend = 'gpu'; allowed: \"compiled\" or \"numpy\""),
        (
            {"solver": {"terms": {"position": {"wieght": 1}}}},
            r"unknown key solver.terms.position.wieght; allowed: enabled, loss, loss_scale, weight",
        ),
        (
            {"solver": {"terms": {"position": {"weight": -1}}}},
            r"solver.terms.position.weight = -1; allowed: a number in \[0, 1e\+06\]",
        ),
        ({"solver": {"terms": {"floor": {"loss": "l1"}}}}, r"solver.terms.floor.loss = 'l1'"),
        ({"solver": {"terms": {"floor": {"enabled": "yes"}}}}, r"enabled = 'yes'; allowed: true or false"),
        (
            {"solver": {"lm": {"max_iterations": 0}}},
            r"solver.lm.max_iterations = 0; allowed: an integer in \[1, 1000\]",
        ),
        ({"solver": {"lm": {"function_tolerance": "small"}}}, r"solver.lm.function_tolerance = 'small'"),
        ({"solver": {"terms": []}}, r"solver.terms = \[\]; allowed: a table"),
    ],
)
def test_bad_config_is_rejected_with_the_key(data: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        parse_config(data)


def test_missing_or_broken_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[solver\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


def test_tracking_section_maps_onto_the_core_options() -> None:
    from mocapd.core.sorting import SortingOptions
    from mocapd.core.suit_binding import BindingOptions
    from mocapd.core.tracking import TrackingOptions

    cfg = load_config()
    assert cfg.tracking.sorting.options() == SortingOptions()
    assert cfg.tracking.enrolment.options() == TrackingOptions()
    assert cfg.tracking.binding.options() == BindingOptions()
    custom = parse_config(
        {"tracking": {"enrolment": {"start_positions": [[0.5, 1.0], [-0.5, 1.0]], "max_subjects": 2}}}
    )
    assert custom.tracking.enrolment.options().start_positions == ((0.5, 1.0), (-0.5, 1.0))
    assert custom.tracking.enrolment.options().max_subjects == 2
    with pytest.raises(ConfigError, match=r"tracking.enrolment.max_subjects = 2.5; allowed: an integer"):
        parse_config({"tracking": {"enrolment": {"max_subjects": 2.5}}})
    with pytest.raises(ConfigError, match=r"unknown key tracking.sorting.radius; allowed: flip_aware, max_interframe"):
        parse_config({"tracking": {"sorting": {"radius": 1}}})
    with pytest.raises(ConfigError, match=r"tracking.enrolment.volume_min = \[1\]; allowed: an array of 2 items"):
        parse_config({"tracking": {"enrolment": {"volume_min": [1]}}})
