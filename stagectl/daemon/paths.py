"""Where the service keeps its files, read once from the command line and the environment.

systemd hands the unit's directories over in ``$RUNTIME_DIRECTORY`` (``RuntimeDirectory=``) and
``$STATE_DIRECTORY`` (``StateDirectory=``), each possibly a ``:``-separated list of which the first entry
counts. :meth:`ServicePaths.from_env` is the only place that reads them.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

__all__ = ["DEFAULT_RUNTIME_DIR", "ServicePaths", "first_dir"]

DEFAULT_RUNTIME_DIR = Path("/run/stagectl")


def first_dir(environ: Mapping[str, str], name: str) -> Path | None:
    """The first entry of the ``:``-separated directory list in ``environ[name]`` (None if unset/empty)."""
    first = environ.get(name, "").split(":")[0]
    return Path(first) if first else None


@dataclass(frozen=True)
class ServicePaths:
    """The service's paths.

    ``config`` the YAML file; ``runtime_dir`` the control socket's directory; ``state_dir`` the persistent
    state (run marker, default telemetry directory), None when neither given nor set by systemd.
    """

    config: Path
    runtime_dir: Path
    state_dir: Path | None = None

    @classmethod
    def from_env(cls, config: str | os.PathLike[str], runtime_dir: str | os.PathLike[str] | None = None,
                 state_dir: str | os.PathLike[str] | None = None,
                 environ: Mapping[str, str] | None = None) -> ServicePaths:
        """Explicit directories win; else ``$RUNTIME_DIRECTORY`` (default ``/run/stagectl``) and
        ``$STATE_DIRECTORY``."""
        env = os.environ if environ is None else environ
        rd = Path(runtime_dir) if runtime_dir else first_dir(env, "RUNTIME_DIRECTORY") or DEFAULT_RUNTIME_DIR
        sd = Path(state_dir) if state_dir else first_dir(env, "STATE_DIRECTORY")
        return cls(Path(config), rd, sd)

    @property
    def marker_dir(self) -> Path:
        """Directory of the run marker: the state directory, else the runtime directory."""
        return self.state_dir if self.state_dir is not None else self.runtime_dir

    def telemetry_dir(self, configured: str | None) -> Path:
        """``daemon.telemetry.directory`` if set, else ``<state dir>/telemetry``, else ``<runtime dir>/telemetry``."""
        return Path(configured) if configured else self.marker_dir / "telemetry"
