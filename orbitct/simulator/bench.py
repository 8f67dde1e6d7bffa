"""The simulated bench: source and detector fixed in the lab, the object moved by a pose ``(R, t)``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.geometry import Panel, ViewGeometry
from orbitct.orbits import Orbit
from orbitct.phantoms.phantom import Phantom
from orbitct.reference_bench import PANEL_PX, SAD_MM, SDD_MM, reference_panel
from orbitct.simulator.beam import Beam
from orbitct.simulator.detector import DetectorModel
from orbitct.simulator.projector import line_integrals


@dataclass(frozen=True)
class SimulatedBench:
    """Fixed source and flat panel (lab reference view ``theta = phi = 0``), the detector's noise model and the
    beam (None: one energy)."""

    sad_mm: float = SAD_MM
    sdd_mm: float = SDD_MM
    panel: Panel = field(default_factory=reference_panel)
    model: DetectorModel = field(default_factory=DetectorModel)
    beam: Beam | None = None

    @classmethod
    def with_panel(cls, size_px: int = PANEL_PX, pitch_mm: float | None = None, **kw: Any) -> SimulatedBench:
        """Bench with the reference panel read out at ``size_px`` (see :func:`~orbitct.reference_bench.reference_panel`)."""
        return cls(panel=reference_panel(size_px, pitch_mm), **kw)

    @property
    def lab_view(self) -> ViewGeometry:
        """The one lab-frame view (source on -y, detector on +y)."""
        return ViewGeometry.from_carm(0.0, 0.0, self.sad_mm, self.sdd_mm, self.panel)

    @property
    def magnification(self) -> float:
        """SDD / SAD."""
        return self.sdd_mm / self.sad_mm

    @property
    def fov_mm(self) -> float:
        """Width of the panel projected to the isocenter."""
        return self.panel.cols * self.panel.pitch_col / self.magnification

    def view(self, R: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0)) -> ViewGeometry:
        """Object-frame view(s) for object pose(s) ``x_lab = R x + t``."""
        return ViewGeometry.from_object_poses(self.lab_view, R, t)

    def nominal_geometry(self, orbit: Orbit) -> ViewGeometry:
        """Nominal views of an orbit on this bench."""
        return orbit.nominal_geometry(self.sad_mm, self.sdd_mm, self.panel)

    def line_integrals(
        self, phantom: Phantom, R: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0), *, supersample: bool | int = True
    ) -> NDArray[np.float32]:
        """Noise-free line integrals of ``phantom`` at object pose ``(R, t)`` (as the panel reads them)."""
        return line_integrals(phantom, self.view(R, t), 0, supersample=supersample, beam=self.beam)

    def render(
        self,
        phantom: Phantom,
        R: ArrayLike,
        t: ArrayLike = (0.0, 0.0, 0.0),
        rng: np.random.Generator | int | None = None,
    ) -> NDArray[np.uint16]:
        """A raw uint16 projection frame of ``phantom`` at object pose ``(R, t)`` (what the panel reads out)."""
        return self.model.expose(
            self.line_integrals(phantom, R, t), np.random.default_rng(rng), self.panel.mean_pitch_mm
        )

    def dark(self, rng: np.random.Generator | int | None = None) -> NDArray[np.uint16]:
        """A raw dark frame."""
        return self.model.dark(np.random.default_rng(rng), self.panel.shape)

    def flat(self, rng: np.random.Generator | int | None = None) -> NDArray[np.uint16]:
        """A raw flat (open-field) frame."""
        return self.model.flat(np.random.default_rng(rng), self.panel.shape, self.panel.mean_pitch_mm)

    def config(self) -> dict[str, Any]:
        """JSON-able description (stored as provenance)."""
        d = self.panel
        return {
            "kind": "simulated_bench",
            "sad_mm": self.sad_mm,
            "sdd_mm": self.sdd_mm,
            "detector": {"rows": d.rows, "cols": d.cols, "pitch_mm": list(d.pitch_mm)},
            "detector_model": self.model.model_dump(mode="json"),
            "beam": "mono" if self.beam is None else self.beam.model_dump(mode="json"),
        }
