"""Plants at the edge of what the simulator can run: the gas spring's step, the shortest step a
plant file may ask for, divergence reported as such, and the closed loop's checks of a plant
against a controller.

A moving mass of a gram with no viscous friction used to be integrated at sim.dt = 0.4 ms,
about 19 times what RK4 allows on the chambers' gas spring, and a closed loop on it reported
``ok`` with chamber pressures of -3.6e39 Pa; a mass of a microgram made the integrator take
0.6 ns steps, so ``simulate`` ran for hours.
"""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pneutune.control.contracts.controller import load_controller
from pneutune.control.contracts.plant import PlantConfig
from pneutune.control.errors import ConfigError
from pneutune.control.plant.params import (
    P_DT,
    gas_spring_step,
    load_sim_plant,
    pack_plant,
    set_step_limits,
)
from pneutune.control.rig.simrig import SimRig
from pneutune.control.rig.wire import RigIOError
from pneutune.control.sim.closed_loop import STATUS_UNSTABLE, prepare_run, run_prepared
from pneutune.control.sim.scenarios import SCENARIOS

ROOT = Path(__file__).resolve().parents[1]
PAPER_YAML = ROOT / "data" / "controller-paper.yaml"
SIMULATE = Path(sys.executable).with_name("simulate")
#: A gram of moving mass and no viscous friction: the gas spring sets the step.
LIGHT = {"mass": 1.0e-3, "friction": {"b_v": 0.0}}


def _short(name: str, duration: float) -> object:
    return dataclasses.replace(SCENARIOS[name], duration=duration)


def test_the_paper_rig_keeps_sim_dt() -> None:
    """Paper rig: stiffness n p_s (A_a^2/V0a + A_b^2/V0b) = 1.2 * 6e5 * (7.854e-3^2/5.036e-5 +
    7.54e-3^2/2.916e-5) = 2.2857e6 N/m, so 2 sqrt(M / k) = 2 sqrt(1.05 / 2.2857e6) = 1.3555 ms,
    above sim.dt = 0.4 ms: the step is the file's, as before the gas-spring bound."""
    cfg = PlantConfig()
    k = 1.2 * 6.0e5 * (7.854e-3**2 / 5.036e-5 + 7.54e-3**2 / 2.916e-5)
    assert gas_spring_step(cfg) == pytest.approx(2.0 * math.sqrt(1.05 / k), rel=1e-12)
    assert gas_spring_step(cfg) == pytest.approx(1.3555e-3, rel=1e-4)
    assert pack_plant(cfg).vec[P_DT] == 4.0e-4


def test_a_gram_of_moving_mass_tracks_instead_of_diverging() -> None:
    """M = 1 g, b_v = 0: the gas spring bounds the step at 2 sqrt(1e-3 / 2.2857e6) = 41.8 us,
    and the paper's controller tracks 2 s of the 0.5 Hz sine with both chambers between
    ambient and supply. The same run at the file's 0.4 ms step (the old integration) diverges,
    and the closed loop reports it ``unstable`` (an absolute pressure at or below zero), not
    ``ok``."""
    cfg = PlantConfig().with_updates(LIGHT)
    assert pack_plant(cfg).vec[P_DT] == pytest.approx(4.183e-5, rel=1e-3)
    controller = load_controller(PAPER_YAML)
    run = prepare_run(_short("sine-0.5hz", 2.0), cfg, seed=1)
    res = run_prepared(run, controller)
    m = res.metrics
    assert m.status == "ok"
    assert 0.99 * cfg.rig.p0 < min(m.p_a_min_Pa, m.p_b_min_Pa)
    assert max(m.p_a_max_Pa, m.p_b_max_Pa) < 1.01 * cfg.rig.p_s
    old = run.vec.copy()
    old[P_DT] = cfg.sim.dt
    set_step_limits(old)
    old.setflags(write=False)
    diverged = run_prepared(dataclasses.replace(run, vec=old), controller)
    assert diverged.metrics.status == STATUS_UNSTABLE
    assert diverged.sensors.shape[0] < run.n


def test_the_simulated_rig_reports_a_diverged_plant() -> None:
    """The same plant at the old 0.4 ms step on the simulated rig that ``record`` and ``deploy``
    drive: an advance that leaves the state unphysical raises the rig's RigIOError (the run
    then faults ``rig_io`` with the fail-safe duties) instead of handing on garbage samples."""
    cfg = PlantConfig().with_updates(LIGHT)
    rig = SimRig(cfg, seed=1)
    vec = rig.params.vec.copy()
    vec[P_DT] = cfg.sim.dt
    set_step_limits(vec)
    rig.params = dataclasses.replace(rig.params, vec=vec)
    rig.write(np.array([1.0, 0.0, 0.0, 1.0]))  # charge A, vent B: the piston flies to x_max
    with pytest.raises(RigIOError, match=r"the simulated plant diverged before t=.*check the "
                                         r"plant file's mass"):
        for _ in range(2000):
            rig.advance()


def test_a_microgram_plant_is_refused_before_it_runs(tmp_path: Path) -> None:
    """M = 1e-6 kg against b_v = 3500 N s/m needs steps of 2 M / b_v = 5.7e-10 s, below the
    simulator's 0.1 us: load_sim_plant refuses it naming the mass, the mode and the step. A
    gram without viscous friction needs 0.47 us on the paper's Stribeck slope, and runs."""
    path = tmp_path / "plant.yaml"
    path.write_text("mass: 1.0e-6\n", encoding="utf-8")
    with pytest.raises(ConfigError) as exc:
        load_sim_plant(str(path))
    assert exc.value.key == "mass"
    assert "sliding friction (b_v 3500 N s/m" in exc.value.message
    assert "needs integration steps of 5.7e-10 s" in exc.value.message
    path.write_text("mass: 1.0e-3\nfriction: {b_v: 0.0}\n", encoding="utf-8")
    assert load_sim_plant(str(path)).mass == 1.0e-3


def _simulate(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(SIMULATE), "--controller", str(PAPER_YAML), *args],
                          capture_output=True, text=True, timeout=300, check=False)


@pytest.mark.parametrize(("text", "needle"), [
    ("mass: 1.0e-6\n", "mass: a moving mass of 1e-06 kg"),
    ("rig: {Ts: 0.002}\n", "controller-paper.yaml: rig.Ts: must equal the rig's Ts = 0.002 s"),
    ("rig: {x_min: 0.0, x_max: 1.0e-6}\n",
     "0.0005 mm either side of mid-stroke within [0.00, 0.00] mm is too short for any scenario"),
])
def test_simulate_refuses_what_deploy_refuses(tmp_path: Path, text: str, needle: str) -> None:
    """``simulate --controller`` on a plant it cannot run, or one the controller is not built
    for (another Ts; a 1 um stroke, too short for even a scaled reference): exit 2, one
    ``error:`` line, as ``deploy`` does."""
    plant = tmp_path / "plant.yaml"
    plant.write_text(text, encoding="utf-8")
    proc = _simulate(["--scenario", "sine-0.5hz", "--plant", str(plant)])
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert needle in lines[0]
