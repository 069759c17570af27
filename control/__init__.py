"""The rig and its controller: plant model and simulator, valves and PWM, friction, Kalman
filters, DARC variants, scenarios, closed loop, MCAP run logs, config schemas and the runtime."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("pneutune")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"
