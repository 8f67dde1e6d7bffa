"""The simulated bench: source and detector fixed in the lab, the object moved by a pose ``(R, t)``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from orbitct.geometry import Detector, ViewGeometry
from orbitct.orbits import Orbit
from orbitct.phantoms.phantom import Phantom
from orbitct.simulator.detector import DetectorModel
from orbitct.simulator.projector import line_integrals

DEFAULT_SAD_MM = 785.0
DEFAULT_SDD_MM = 1200.0
DEFAULT_DETECTOR_PX = 768
DEFAULT_PITCH_MM = 0.556
PANEL_MM = 427.0  # square panel side


def bench_detector(size_px: int = DEFAULT_DETECTOR_PX, pitch_mm: float | None = None) -> Detector:
    """Square detector of ``size_px`` pixels on the 427 mm panel: 0.556 mm at 768 px, else 427 mm / size."""
    if int(size_px) < 8:
        raise ValueError(f"detector size must be at least 8 px, got {size_px}")
    if pitch_mm is not None:
        p = float(pitch_mm)
    else:
        p = DEFAULT_PITCH_MM if int(size_px) == DEFAULT_DETECTOR_PX else PANEL_MM / int(size_px)
    return Detector(int(size_px), int(size_px), p, p)


@dataclass(frozen=True)
class SimulatedBench:
    """Fixed source and flat panel (lab reference view ``theta = phi = 0``) plus the detector's noise model."""

    sad_mm: float = DEFAULT_SAD_MM
    sdd_mm: float = DEFAULT_SDD_MM
    detector: Detector = field(default_factory=bench_detector)
    model: DetectorModel = field(default_factory=DetectorModel)

    @classmethod
    def with_detector(cls, size_px: int = DEFAULT_DETECTOR_PX, pitch_mm: float | None = None, **kw: Any) -> "SimulatedBench":
        """Bench with a square detector of ``size_px`` (see :func:`bench_detector`)."""
        return cls(detector=bench_detector(size_px, pitch_mm), **kw)

    @property
    def lab_view(self) -> ViewGeometry:
        """The one lab-frame view (source on -y, detector on +y)."""
        return ViewGeometry.from_carm(0.0, 0.0, self.sad_mm, self.sdd_mm, self.detector)

    @property
    def magnification(self) -> float:
        """SDD / SAD."""
        return self.sdd_mm / self.sad_mm

    @property
    def fov_mm(self) -> float:
        """Width of the panel projected to the isocenter."""
        return self.detector.cols * self.detector.pitch_col / self.magnification

    def view(self, R: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0)) -> ViewGeometry:
        """Object-frame view(s) for object pose(s) ``x_lab = R x + t``."""
        return ViewGeometry.from_object_poses(self.lab_view, R, t)

    def nominal_geometry(self, orbit: Orbit) -> ViewGeometry:
        """Nominal views of an orbit on this bench."""
        return orbit.nominal_geometry(self.sad_mm, self.sdd_mm, self.detector)

    def line_integrals(
        self, phantom: Phantom, R: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0), *, supersample: bool | int = True
    ) -> NDArray[np.float32]:
        """Noise-free line integrals of ``phantom`` at object pose ``(R, t)``."""
        return line_integrals(phantom, self.view(R, t), 0, supersample=supersample)

    def render(
        self, phantom: Phantom, R: ArrayLike, t: ArrayLike = (0.0, 0.0, 0.0), rng: np.random.Generator | int | None = None
    ) -> NDArray[np.uint16]:
        """A raw uint16 projection frame of ``phantom`` at object pose ``(R, t)`` (what the panel reads out)."""
        return self.model.expose(self.line_integrals(phantom, R, t), np.random.default_rng(rng))

    def dark(self, rng: np.random.Generator | int | None = None) -> NDArray[np.uint16]:
        """A raw dark frame."""
        return self.model.dark(np.random.default_rng(rng), self.detector.shape)

    def flat(self, rng: np.random.Generator | int | None = None) -> NDArray[np.uint16]:
        """A raw flat (open-field) frame."""
        return self.model.flat(np.random.default_rng(rng), self.detector.shape)

    def config(self) -> dict[str, Any]:
        """JSON-able description (stored as provenance)."""
        d = self.detector
        return {
            "kind": "simulated_bench",
            "sad_mm": self.sad_mm,
            "sdd_mm": self.sdd_mm,
            "detector": {"rows": d.rows, "cols": d.cols, "pitch_mm": list(d.pitch_mm)},
            "detector_model": self.model.model_dump(mode="json"),
        }
