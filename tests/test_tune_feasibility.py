"""The feasibility check before a study: a tune never ends with nothing.

Models come from ``model_from_plant`` (the truth model of a plant, every range ±20 %), edited so
that one range end holds a plant no controller tracks (a break-away force of 3 kN against the
~3.9 kN a 6 bar supply gives on the paper's piston), or so that even the nominal plant cannot be
tracked (a viscous coefficient of 8e4 N s/m needs 4.4 kN at the 0.5 Hz sine's 55 mm/s).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
from tune_helpers import QUICK, load_study, run_tune

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.model import ModelConfig, save_model
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.sim.truth import model_from_plant
from pneutune.tune.feasibility import InfeasibleModelError, check_feasibility
from pneutune.tune.objective import ObjectiveSettings
from pneutune.tune.plants import draw_plants, uncertainty_box

SETTINGS = ObjectiveSettings(scenarios=("sine-0.5hz",), n_draws=3, duration=4.0)


def _edited(plant: PlantConfig, **friction_ranges: Any) -> ModelConfig:
    data = model_from_plant(plant).to_dict()
    data["friction"]["ranges"].update(friction_ranges)
    return ModelConfig.model_validate(data)


def test_a_sane_model_is_not_narrowed() -> None:
    """The truth model's ±20 % box is trackable by the paper's gains: nothing changes."""
    feas = check_feasibility(model_from_plant(PlantConfig()), 1, SETTINGS)
    assert feas.box == ()
    assert feas.steps == ()
    assert feas.reference == "the paper's gains"
    assert feas.notes() == []


def test_an_untrackable_range_end_is_named_and_narrowed() -> None:
    """F_S up to 3 kN: the slow corner sticks; the check names F_S and narrows only it."""
    model = _edited(PlantConfig(), F_S=[60.0, 3000.0])
    feas = check_feasibility(model, 1, SETTINGS)
    first = feas.steps[0]
    assert first.draw == 1 and first.label == "slow"
    assert first.alone
    assert [k for k, _, _ in first.culprits] == ["friction.F_S"]
    assert first.culprits[0][1] == pytest.approx(3000.0)
    assert first.culprits[0][2]  # at its range end
    assert "friction.F_S = 3000 N at its range end alone makes the paper's gains fail" in \
        feas.notes()[0]
    keys = {k for k, _, _ in feas.box}
    assert keys == {"friction.F_S"}
    (_, lo, hi), = feas.box
    assert lo == pytest.approx(60.0) and 75.0 <= hi < 3000.0
    # the narrowed box is what the draws use
    st = dataclasses.replace(SETTINGS, box=feas.box)
    box = {c.key: c for c in uncertainty_box(model, st.box_dict())}
    assert box["friction.F_S"].high == pytest.approx(hi)
    assert max(d.plant.friction.F_S for d in draw_plants(model, 3, 1, st.box_dict())) <= hi


def test_tune_completes_on_that_model_and_says_what_it_changed(tmp_path: Path) -> None:
    """Exit 0 with a controller; the paper's trial completes; provenance and report say why."""
    path = tmp_path / "model.yaml"
    save_model(_edited(PlantConfig(), F_S=[60.0, 3000.0]), path)
    out = tmp_path / "out"
    code, res, err = run_tune(["--model", str(path), "--trials", "6", "--out", str(out),
                               "--draws", "3", *QUICK[:2], *QUICK[4:]])
    assert code == 0, err
    assert res is not None and res["narrowed"][0][0] == "friction.F_S"
    study = load_study(str(out / "study.journal"), res["study"])
    assert study.trials[0].state.name == "COMPLETE"  # the paper's gains
    prov = load_controller(out / "controller.yaml").provenance
    assert prov is not None and prov.notes is not None
    assert any("friction.F_S" in n for n in prov.notes)
    assert "## What tune had to change" in (out / "report.md").read_text()


def test_an_untrackable_nominal_plant_is_bad_input(tmp_path: Path) -> None:
    """b_v = 8e4 N s/m: nothing tracks the nominal plant -> exit 2, one error line."""
    plant = PlantConfig().with_updates({"friction": {"b_v": 8.0e4}})
    model = model_from_plant(plant)
    with pytest.raises(InfeasibleModelError, match="the nominal plant cannot be tracked"):
        check_feasibility(model, 1, SETTINGS)
    path = tmp_path / "model.yaml"
    save_model(model, path)
    code, res, err = run_tune(["--model", str(path), "--trials", "4", "--out",
                               str(tmp_path / "out"), *QUICK])
    assert code == 2 and res is None
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: "), err
    assert "cannot be tracked" in lines[0]
