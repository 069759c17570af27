"""Scenarios scaled to a short stroke.

Table 1's references swing 17.5 mm either side of mid-stroke, so they need about 35 mm between
the position limits. On a shorter axis ``tune``, ``deploy`` and ``simulate`` scale every
reference about mid-stroke to span 0.7 of the room (the paper rig's 17.5 of 25 mm) and Table
1's figures alike; where the references fit, nothing changes.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from rig_helpers import PAPER_YAML
from tune_helpers import load_study, only_study_name, run_tune, write_truth_model

from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ExperimentError
from pneutune.control.sim.scenarios import (
    SCENARIOS,
    STROKE_SHARE,
    fit_to_limits,
    stroke_scale,
)
from pneutune.control.sim.table import format_table
from pneutune.tune.objective import ObjectiveSettings, reference_figures

DEPLOY = str(Path(sys.executable).with_name("deploy"))
TS = 0.004
#: The 30 mm axis of these tests: stroke ends -1.5 and 28.5 mm, mid-stroke 13.5 mm, 15 mm of
#: room either side; 0.7 of it is 10.5 mm = 0.6 x 17.5 mm.
X_MIN, X_MAX, SHORT_SCALE = -0.0015, 0.0285, 0.6


def test_a_scaled_reference_is_the_papers_times_the_factor() -> None:
    """Position about the centre, speed and acceleration scale by the factor (to rounding);
    the figures too; the plant changes (payload, force steps) and the name stay."""
    center = 0.0135
    for sc in SCENARIOS.values():
        small = sc.scaled(0.6)
        r0, r1 = sc.reference_array(TS, center), small.reference_array(TS, center)
        np.testing.assert_allclose(r1[:, 0] - center, 0.6 * (r0[:, 0] - center), rtol=0.0,
                                   atol=1e-15)
        np.testing.assert_allclose(r1[:, 1:], 0.6 * r0[:, 1:], rtol=1e-15, atol=0.0)
        assert (small.name, small.plant_updates, small.duration) == (sc.name, sc.plant_updates,
                                                                     sc.duration)
        assert small.scale == 0.6
        ep, erms = reference_figures(sc)
        assert reference_figures(small) == pytest.approx((0.6 * ep, 0.6 * erms), rel=1e-15)
        assert sc.scaled(1.0) is sc
        assert small.scaled(0.5).scale == pytest.approx(0.3, rel=1e-15)
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ExperimentError, match="must be in"):
            SCENARIOS["sine-0.5hz"].scaled(bad)


def test_stroke_scale_is_one_where_table1_fits_and_keeps_the_papers_share_below() -> None:
    """The paper's rig ([-1.5, 48.5] mm): 1 (the references as they are). 30 mm: 0.6, by hand
    above. 35.1 mm: still 1 (the references fit, with 0.05 mm to spare: the paper's, as
    before). 34 mm: 0.7 x 17 / 17.5 = 0.68. A 2 mm stroke (0.7 mm references) is refused."""
    table1 = list(SCENARIOS.values())
    assert STROKE_SHARE == pytest.approx(0.7, rel=1e-15)
    assert stroke_scale(table1, TS, 0.0235, -0.0015, 0.0485) == 1.0
    assert stroke_scale(table1, TS, 0.0135, X_MIN, X_MAX) == pytest.approx(SHORT_SCALE,
                                                                           rel=1e-12)
    assert stroke_scale(table1, TS, 0.01755, 0.0, 0.0351) == 1.0
    assert stroke_scale(table1, TS, 0.017, 0.0, 0.034) == pytest.approx(0.68, rel=1e-12)
    fitted, factor = fit_to_limits(table1, TS, 0.0135, X_MIN, X_MAX)
    for sc in fitted:
        x = sc.reference_array(TS, 0.0135)[:, 0]
        assert x.min() >= X_MIN + 0.3 * 0.015 - 1e-12 and x.max() <= X_MAX - 0.3 * 0.015 + 1e-12
    assert factor == pytest.approx(SHORT_SCALE, rel=1e-12)
    with pytest.raises(ExperimentError, match="too short for any scenario"):
        stroke_scale(table1, TS, -0.0005, -0.0015, 0.0005)
    with pytest.raises(ExperimentError, match="not inside the limits"):
        stroke_scale(table1, TS, 0.05, -0.0015, 0.0285)


def test_the_setting_is_stored_only_when_it_scales() -> None:
    """Studies made before the setting existed keep comparing equal: 1 is not written."""
    assert "amplitude_scale" not in ObjectiveSettings().to_dict()
    st = ObjectiveSettings(amplitude_scale=0.6)
    assert st.to_dict()["amplitude_scale"] == 0.6
    assert ObjectiveSettings.from_dict(st.to_dict()) == st


def test_a_30mm_axis_is_tuned_and_deployed_on_scaled_references(tmp_path: Path) -> None:
    """tune on the truth model of a 30 mm axis: exit 0, the scale (0.6, by hand above) in its
    output, the controller's provenance, the report and the stored study; deploy of that
    controller on the 30 mm plant runs the same scaled references, with a warning, and stays
    within the stroke (status ok)."""
    model = write_truth_model(tmp_path)
    data = yaml.safe_load(model.read_text(encoding="utf-8"))
    data["rig"]["x_max"] = X_MAX
    model.write_text(yaml.safe_dump(data), encoding="utf-8")
    out = tmp_path / "tune"
    code, res, err = run_tune(["--model", str(model), "--trials", "3", "--draws", "2",
                               "--scenarios", "sine-0.5hz", "--duration", "2", "--jobs", "1",
                               "--seed", "1", "--out", str(out)])
    assert code == 0, err
    assert res is not None and res["amplitude_scale"] == pytest.approx(SHORT_SCALE, rel=1e-12)
    assert "is scaled by 0.600 to 10.50 mm" in err
    controller = yaml.safe_load((out / "controller.yaml").read_text(encoding="utf-8"))
    assert any("scaled by 0.600" in n for n in controller["provenance"]["notes"])
    assert controller["limits"]["x_max"] == X_MAX
    assert "**Short stroke.**" in (out / "report.md").read_text(encoding="utf-8")
    storage = str(out / "study.journal")
    study = load_study(storage, only_study_name(storage))
    assert study.user_attrs["pneutune"]["objective"]["amplitude_scale"] == pytest.approx(
        SHORT_SCALE, rel=1e-12)

    plant = PlantConfig().model_dump(by_alias=True, mode="json")
    plant["rig"]["x_max"] = X_MAX
    plant_path = tmp_path / "plant.yaml"
    plant_path.write_text(yaml.safe_dump(plant), encoding="utf-8")
    proc = subprocess.run([DEPLOY, str(out / "controller.yaml"), "--rig", f"sim:{plant_path}",
                           "--scenario", "sine-0.5hz", "--duration", "2", "--json"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    dep = json.loads(proc.stdout)
    scaled = [w for w in dep["warnings"] if w["code"] == "reference_scaled"]
    assert len(scaled) == 1 and "scaled by 0.600 to 10.50 mm" in scaled[0]["message"]
    assert all(r["status"] == "ok" for r in dep["scenarios"].values()), dep["scenarios"]


def test_the_table_says_when_table1_is_scaled() -> None:
    """The footnote of the metrics table names the factor only when there is one."""
    m = {"E_p_mm": 0.2, "E_rms_mm": 0.1, "switches_per_s": 10.0, "p_a_max_Pa": 4.5e5,
         "p_b_max_Pa": 4.6e5, "status": "ok", "theta_in_bounds": True}
    rows = [("sine-0.5hz", m, (0.6 * 0.42, 0.6 * 0.19))]
    assert "times" not in format_table(rows, "t")
    text = format_table(rows, "t", SHORT_SCALE)
    assert "0.25        0.11" in text
    assert "measured on their rig, times 0.600 with the references scaled" in text


def test_a_driver_told_only_the_name_starts_where_deploy_scales_to(tmp_path: Path) -> None:
    """The smooth square starts at its low level: 17.5 mm below mid-stroke unscaled, outside a
    30 mm stroke (-4 mm against -1.5 mm). The pipe driver, which gets only the scenario's
    name, puts the piston at the scaled start (13.5 - 10.5 = 3 mm), so the paper's controller
    (limits [-1.5, 48.5] mm, narrowed to the rig's stroke) runs it without a position fault."""
    plant = PlantConfig().model_dump(by_alias=True, mode="json")
    plant["rig"]["x_max"] = X_MAX
    plant_path = tmp_path / "plant.yaml"
    plant_path.write_text(yaml.safe_dump(plant), encoding="utf-8")
    proc = subprocess.run([DEPLOY, str(PAPER_YAML), "--rig", f"pipe-sim:{plant_path}",
                           "--scenario", "square-0.5hz", "--duration", "1", "--json"],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    dep = json.loads(proc.stdout)
    assert dep["faults"] == []
    assert [w["code"] for w in dep["warnings"]].count("reference_scaled") == 1
    assert dep["scenarios"]["square-0.5hz"]["status"] == "ok"
