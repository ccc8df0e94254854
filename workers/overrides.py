"""A run's derived overrides: logged as they are known, recorded in the store at the end.

The values known before the run (:func:`schlieren.pipeline.overrides.bind_run`,
:func:`~schlieren.pipeline.overrides.session_overrides`) are logged when the run starts;
those the regularisation stage chooses are logged when its receipt reaches the lead
process (serial loop or Dask alike), the cameras' pre-smoothing when every camera's
capture receipt has. At the end every override goes into the store's root
attribute ``derived`` (``{parameter: {requested, effective, unit, from}}``, docs/store.md);
a resumed run whose regularisation task had already run reads the chosen values back
from the stored arrays if the attribute lacks them.
"""

from __future__ import annotations

import logging

import numpy as np

from schlieren.pipeline.overrides import Override, presmooth_override, records, regularisation_overrides
from schlieren.pipeline.stages import RunConfig, middle_frame

__all__ = ["RunOverrides", "DERIVED_ATTR"]

log = logging.getLogger("schlieren.workers.run")  # the run's logger: its lines sit with the run's

#: Root attribute of the store holding the overrides.
DERIVED_ATTR = "derived"


class RunOverrides:
    """The overrides of one run: :meth:`start` logs those known before it, :meth:`receipt`
    (a receipt callback) those the regularisation stage chooses, :meth:`attrs` gives the
    store attribute."""

    def __init__(self, cfg: RunConfig, overrides: list[Override], n_frames: int, n_cameras: int = 0):
        self.cfg = cfg
        self.overrides = list(overrides)
        self.n_frames = int(n_frames)
        self.n_cameras = int(n_cameras)
        self.chosen: list[Override] = []
        self.presmooth: dict[int, float] = {}  # camera -> the capture stage's choice
        self.smoothing: list[Override] = []

    def start(self) -> None:
        for o in self.overrides:
            log.info("%s", o.line())

    def receipt(self, r: dict) -> None:
        """Log the regularisation stage's choices when its (not skipped) receipt arrives, and
        the cameras' pre-smoothing once every camera's capture receipt has."""
        if r.get("stage") == "capture" and "presmooth" in r and not r.get("skipped"):
            self.presmooth[int(r["index"][0])] = float(r["presmooth"])
            if len(self.presmooth) == self.n_cameras:
                self.smoothing = presmooth_override(self.cfg, [self.presmooth[c] for c in range(self.n_cameras)])
                for o in self.smoothing:
                    log.info("%s", o.line())
            return
        if r.get("stage") != "regularisation" or r.get("skipped") or "reg_weight" not in r:
            return
        self.chosen = regularisation_overrides(self.cfg, r["reg_weight"], r.get("flow_window") or [],
                                               noise=r.get("rhs_noise"), frame=self._frame())
        for o in self.chosen:
            log.info("%s", o.line())

    def _frame(self) -> int | None:
        return middle_frame(self.n_frames) if self.n_frames > 0 else None

    def attrs(self, store) -> dict:
        """The ``derived`` attribute: this run's overrides over the store's previous ones; the
        regularisation stage's from its receipt, else from the stored arrays (a resumed run)."""
        out = dict(store.attrs.get(DERIVED_ATTR) or {})
        out.update(records(self.overrides))
        chosen = self.chosen or self._stored_choice(store, out)
        out.update(records(chosen))
        out.update(records(self.smoothing or self._stored_presmooth(store, out)))
        return out

    def _stored_presmooth(self, store, known: dict) -> list[Override]:
        """The cameras' pre-smoothing read back from ``presmooth`` when the attribute lacks it
        and every camera's capture task has completed (a resumed run)."""
        if "flow.presmooth" in known or not self.n_cameras or \
                not all(store.is_done("capture", (c,)) for c in range(self.n_cameras)):
            return []
        try:
            values = np.asarray(store.read("presmooth", ()), dtype=np.float64)
        except Exception:  # noqa: BLE001 - a damaged chunk: its readers report it; the attribute waits
            log.debug("derived: the stored pre-smoothing is unreadable", exc_info=True)
            return []
        return presmooth_override(self.cfg, values)

    def _stored_choice(self, store, known: dict) -> list[Override]:
        """The regularisation stage's choice read back from ``reg_weight`` / ``flow_window`` when
        the attribute lacks it and the stage's task has completed."""
        wanted = [o.path for o in regularisation_overrides(self.cfg, np.nan, [])]
        if not wanted or all(p in known for p in wanted) or not store.is_done("regularisation", ()):
            return []
        try:
            weight = float(np.asarray(store.read("reg_weight", ()))[0])
            window = np.asarray(store.read("flow_window", ()), dtype=np.float64)
            noise = np.asarray(store.read("rhs_noise", ()), dtype=np.float64)
        except Exception:  # noqa: BLE001 - a damaged chunk: its readers report it; the attribute waits
            log.debug("derived: the regularisation stage's values are unreadable", exc_info=True)
            return []
        return regularisation_overrides(self.cfg, weight, window, noise=noise, frame=self._frame())
