"""Per-frame rigid motion errors to inject on top of an orbit: ``bench`` (the paper's), ``none``, ``custom``.

How an error applies (the one definition everyone uses): frame ``n`` carries a rigid
transform ``E_n = (R_e, t_e)`` in the **lab frame, about the nominal isocenter** (lab origin).
``R_e = R_x(pitch) R_y(roll) R_z(yaw)`` (PI's U, V, W order), with lab axes x = tilt axis
(pitch), y = beam axis, source on -y (roll), z = rotation-stage axis (yaw). The true object
pose is the error applied after the nominal pose::

    x_lab = R_e (R_nom x_obj + t_nom) + t_e          i.e. true pose = E_n o nominal pose

so an executor adds it to the commanded pose as ``R_cmd = R_e R_nom``, ``t_cmd = R_e t_nom + t_e``
before splitting it into stage and hexapod (``orbitct.kinematics.split_pose``). Seen from the
object (``RigidErrors.apply_to_geometry``) the source and detector move by the inverse.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from orbitct.geometry import ViewGeometry
from orbitct.orbits import Orbit
from orbitct.rotations import rot_xyz, xyz_angles

__all__ = [
    "PROFILE_NAMES",
    "BenchProfile",
    "ComposedProfile",
    "CustomProfile",
    "ErrorProfile",
    "ErrorProfileError",
    "NoErrors",
    "RigidErrors",
    "compose",
    "make_profile",
    "profile_from_json",
]

PROFILE_NAMES = ("bench", "none", "custom")
Triple = tuple[float, float, float]


class ErrorProfileError(ValueError):
    """Unknown profile name or bad profile parameter."""


def _frozen(a: ArrayLike, shape_tail: tuple[int, ...], name: str) -> NDArray[np.float64]:
    arr = np.array(a, dtype=float)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise ErrorProfileError(f"{name}: expected shape (N, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class RigidErrors:
    """Per-frame errors: ``angles`` (N, 3) = pitch, roll, yaw (rad) and ``shift_mm`` (N, 3) = x, y, z.

    One axis order everywhere (``as_array``, ``/acquisition/injected_errors``, ``/truth/errors``):
    pitch, roll, yaw, x, y, z.
    """

    angles: NDArray[np.float64]
    shift_mm: NDArray[np.float64]

    def __post_init__(self) -> None:
        object.__setattr__(self, "angles", _frozen(self.angles, (3,), "angles"))
        object.__setattr__(self, "shift_mm", _frozen(self.shift_mm, (3,), "shift_mm"))
        if self.angles.shape != self.shift_mm.shape:
            raise ErrorProfileError(f"angles {self.angles.shape} and shift_mm {self.shift_mm.shape} differ in length")

    @classmethod
    def zeros(cls, n_frames: int) -> RigidErrors:
        """No error on ``n_frames`` frames."""
        return cls(np.zeros((n_frames, 3)), np.zeros((n_frames, 3)))

    @classmethod
    def from_transforms(cls, R: ArrayLike, t: ArrayLike) -> RigidErrors:
        """Errors from rotations ``(N, 3, 3)`` and shifts ``(N, 3)``."""
        return cls(xyz_angles(R), np.asarray(t, dtype=float))

    def as_array(self) -> NDArray[np.float64]:
        """``(N, 6)``: pitch, roll, yaw (rad), x, y, z (mm)."""
        return np.concatenate([self.angles, self.shift_mm], axis=1)

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return int(self.angles.shape[0])

    @property
    def pitch(self) -> NDArray[np.float64]:
        """Rotation about lab x (tilt axis), rad."""
        return self.angles[:, 0]

    @property
    def roll(self) -> NDArray[np.float64]:
        """Rotation about lab y (beam axis), rad."""
        return self.angles[:, 1]

    @property
    def yaw(self) -> NDArray[np.float64]:
        """Rotation about lab z (rotation-stage axis), rad."""
        return self.angles[:, 2]

    def transforms(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``R (N, 3, 3) = R_x(pitch) R_y(roll) R_z(yaw)`` and ``t (N, 3)`` (mm), lab frame about the isocenter."""
        return rot_xyz(self.pitch, self.roll, self.yaw), self.shift_mm.copy()

    def then(self, other: RigidErrors) -> RigidErrors:
        """Errors of ``self`` followed by those of ``other``: ``E = E_other o E_self`` per frame."""
        if other.n_frames != self.n_frames:
            raise ErrorProfileError(f"cannot compose errors over {self.n_frames} and {other.n_frames} frames")
        Ra, ta = self.transforms()
        Rb, tb = other.transforms()
        return RigidErrors.from_transforms(Rb @ Ra, np.einsum("nij,nj->ni", Rb, ta) + tb)

    __add__ = then

    def true_poses(
        self, R_nominal: ArrayLike, t_nominal: ArrayLike | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """True object poses ``(R_e R_nom, R_e t_nom + t_e)`` from nominal ones."""
        Rn = np.asarray(R_nominal, dtype=float).reshape(self.n_frames, 3, 3)
        tn = np.zeros((self.n_frames, 3)) if t_nominal is None else np.asarray(t_nominal, float).reshape(-1, 3)
        Re, te = self.transforms()
        return Re @ Rn, np.einsum("nij,nj->ni", Re, tn) + te

    def apply_to_geometry(self, geometry: ViewGeometry, reference: ViewGeometry | None = None) -> ViewGeometry:
        """True views from nominal ones: each view's object moved by its error in the lab frame.

        The nominal pose of view ``n`` is recovered from its detector axes relative to the
        ``reference`` (lab) view, by default the ``theta = phi = 0`` view (columns +x, rows -z).
        """
        if geometry.n_views != self.n_frames:
            raise ErrorProfileError(f"geometry has {geometry.n_views} views, errors have {self.n_frames} frames")
        if reference is None:
            B_ref = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns u^, v^, u^ x v^
        else:
            B_ref = _view_basis(reference.u, reference.v)[0]
        B = _view_basis(geometry.u, geometry.v)
        R_nom = B_ref @ np.swapaxes(B, 1, 2)  # lab <- object
        Re, te = self.transforms()
        M = np.swapaxes(R_nom, 1, 2) @ np.swapaxes(Re, 1, 2) @ R_nom
        m = -np.einsum("nij,nj->ni", np.swapaxes(R_nom, 1, 2) @ np.swapaxes(Re, 1, 2), te)
        ok = geometry.valid
        M[~ok] = np.eye(3)
        m[~ok] = 0.0
        return geometry.transformed(M, m)

    def summary(self) -> dict[str, float]:
        """Peak absolute angle (deg) and shift (mm) per axis."""
        a = np.degrees(np.abs(self.angles)).max(axis=0) if self.n_frames else np.zeros(3)
        s = np.abs(self.shift_mm).max(axis=0) if self.n_frames else np.zeros(3)
        return {
            "pitch_deg": float(a[0]),
            "roll_deg": float(a[1]),
            "yaw_deg": float(a[2]),
            "x_mm": float(s[0]),
            "y_mm": float(s[1]),
            "z_mm": float(s[2]),
        }


def _view_basis(u: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    uh = u / np.linalg.norm(u, axis=1, keepdims=True)
    vh = v / np.linalg.norm(v, axis=1, keepdims=True)
    return np.stack([uh, vh, np.cross(uh, vh)], axis=-1)


_DRAW_ORDER = [1, 0, 2]  # random draws run roll, pitch, yaw (their historical order): same seed, same errors


def _waves(
    rng: np.random.Generator, phase_of: NDArray[np.float64], amplitude: ArrayLike, noise: ArrayLike
) -> NDArray[np.float64]:
    """``amplitude * sin(phase_of + random phase) + U(-noise, noise)`` for 3 axes, (N, 3)."""
    n = phase_of.shape[0]
    phases = rng.uniform(0.0, 2 * np.pi, 3)
    w = rng.uniform(-1.0, 1.0, (n, 3))
    return np.asarray(amplitude, float) * np.sin(phase_of[:, None] + phases) + np.asarray(noise, float) * w


def _angle_waves(
    rng: np.random.Generator, phase_of: NDArray[np.float64], amplitude: ArrayLike, noise: ArrayLike
) -> NDArray[np.float64]:
    """:func:`_waves` for pitch, roll, yaw amplitudes, drawn in :data:`_DRAW_ORDER`."""
    a, w = np.asarray(amplitude, float)[_DRAW_ORDER], np.asarray(noise, float)[_DRAW_ORDER]
    return _waves(rng, phase_of, a, w)[:, _DRAW_ORDER]


class ErrorProfile:
    """Something that samples per-frame :class:`RigidErrors` for an orbit (seeded, reproducible)."""

    name: str = ""
    seed: int = 0

    def sample(self, orbit: Orbit) -> RigidErrors:
        """Errors for every frame of ``orbit``."""
        raise NotImplementedError

    def to_json(self) -> dict[str, Any]:
        """Name, seed and parameters."""
        return {"name": self.name, "seed": self.seed}

    def __add__(self, other: ErrorProfile) -> ComposedProfile:
        return compose(self, other)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.to_json()})"


class NoErrors(ErrorProfile):
    """No error at all."""

    name = "none"

    def __init__(self, seed: int = 0) -> None:
        self.seed = int(seed)

    def sample(self, orbit: Orbit) -> RigidErrors:
        return RigidErrors.zeros(orbit.n_frames)


class CustomParams(BaseModel):
    """Per axis: ``amplitude * sin(2 pi cycles * n / N + random phase) + U(-noise, noise)``."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    angle_amplitude_deg: Triple = Field((0.0, 0.0, 0.0), description="pitch, roll, yaw sine amplitudes")
    angle_cycles: float = Field(1.0, ge=0, le=1000, description="sine periods over the scan")
    angle_noise_deg: Triple = Field((0.0, 0.0, 0.0), description="pitch, roll, yaw uniform noise half-widths")
    shift_amplitude_mm: Triple = Field((0.0, 0.0, 0.0), description="x, y, z sine amplitudes")
    shift_cycles: float = Field(1.0, ge=0, le=1000, description="sine periods over the scan")
    shift_noise_mm: Triple = Field((0.0, 0.0, 0.0), description="x, y, z uniform noise half-widths")


class CustomProfile(ErrorProfile):
    """Sines plus uniform noise with the given amplitudes and frequencies."""

    name = "custom"

    def __init__(self, seed: int = 0, **params: Any) -> None:
        self.seed = int(seed)
        self.params = _validated(CustomParams, "custom", params)

    def sample(self, orbit: Orbit) -> RigidErrors:
        p = self.params
        rng = np.random.default_rng([self.seed, 2])
        s = 2 * np.pi * np.arange(orbit.n_frames) / max(orbit.n_frames, 1)
        ang = _angle_waves(rng, p.angle_cycles * s, np.radians(p.angle_amplitude_deg), np.radians(p.angle_noise_deg))
        sh = _waves(rng, p.shift_cycles * s, p.shift_amplitude_mm, p.shift_noise_mm)
        return RigidErrors(ang, sh)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "seed": self.seed, **self.params.model_dump(mode="json")}


class BenchParams(BaseModel):
    """Parameters of the paper's bench profile (defaults reproduce Experiment A)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    angle_scale: float = Field(1.0, ge=0, le=100, description="angular amplitude in units of the per-frame step")
    sag_fraction: float = Field(0.5, ge=0, le=1, description="share of the amplitude that is the sinusoidal sag")
    shift_amplitude_mm: float = Field(8.0, ge=0, le=100, description="isocenter shift sine amplitude")
    shift_noise_mm: float = Field(2.0, ge=0, le=100, description="isocenter shift uniform noise half-width")
    shift_cycles: float = Field(1.0, ge=0, le=1000, description="shift sine periods over the scan")


class BenchProfile(ErrorProfile):
    """The paper's bench profile: step-sized angular errors with a sag sine, 8 mm sine + +-2 mm shifts.

    Angular amplitude ``A`` per axis: pitch = mean tilt step per frame, yaw = mean rotation
    step (an axis that does not move borrows the other's step), roll = the larger of the two.
    Angle error = ``A (f sin(theta_n + phase) + (1 - f) U(-1, 1))``, ``f = sag_fraction``, so
    ``|error| <= A`` and the sag follows the gantry rotation angle ``theta_n`` (gravity).
    Shift per axis = ``8 mm sin(2 pi n / N + phase) + U(-2, 2) mm``.
    """

    name = "bench"

    def __init__(self, seed: int = 0, **params: Any) -> None:
        self.seed = int(seed)
        self.params = _validated(BenchParams, "bench", params)

    def amplitudes(self, orbit: Orbit) -> NDArray[np.float64]:
        """Pitch, roll, yaw amplitudes (rad) for ``orbit``."""
        rot, tilt = orbit.step_sizes()
        yaw = rot if rot > 0 else tilt
        pitch = tilt if tilt > 0 else rot
        return self.params.angle_scale * np.array([pitch, max(rot, tilt), yaw])

    def sample(self, orbit: Orbit) -> RigidErrors:
        p = self.params
        rng = np.random.default_rng([self.seed, 1])
        A = self.amplitudes(orbit)
        ang = _angle_waves(rng, orbit.theta, A * p.sag_fraction, A * (1.0 - p.sag_fraction))
        s = 2 * np.pi * p.shift_cycles * np.arange(orbit.n_frames) / max(orbit.n_frames, 1)
        sh = _waves(rng, s, np.full(3, p.shift_amplitude_mm), np.full(3, p.shift_noise_mm))
        return RigidErrors(ang, sh)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "seed": self.seed, **self.params.model_dump(mode="json")}


class ComposedProfile(ErrorProfile):
    """Profiles applied one after another: ``(a + b)`` = ``a`` first, then ``b`` on top."""

    name = "composed"

    def __init__(self, parts: list[ErrorProfile]) -> None:
        self.parts = list(parts)
        self.seed = self.parts[0].seed if self.parts else 0

    def sample(self, orbit: Orbit) -> RigidErrors:
        out = RigidErrors.zeros(orbit.n_frames)
        for p in self.parts:
            out = out.then(p.sample(orbit))
        return out

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "parts": [p.to_json() for p in self.parts]}


def compose(*profiles: ErrorProfile) -> ComposedProfile:
    """One profile applying ``profiles`` in order."""
    parts: list[ErrorProfile] = []
    for p in profiles:
        parts.extend(p.parts if isinstance(p, ComposedProfile) else [p])
    return ComposedProfile(parts)


def _validated(model: type[BaseModel], name: str, params: dict[str, Any]) -> Any:
    try:
        return model(**params)
    except ValidationError as exc:
        msg = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise ErrorProfileError(
            f"error profile {name!r}: {msg} (parameters: {', '.join(model.model_fields)})"
        ) from None


def make_profile(name: Literal["bench", "none", "custom"] | str, seed: int = 0, **params: Any) -> ErrorProfile:
    """Error profile ``bench``, ``none`` or ``custom`` with a seed and its parameters."""
    if name == "bench":
        return BenchProfile(seed, **params)
    if name == "none":
        if params:
            raise ErrorProfileError(f"error profile 'none' takes no parameters, got {sorted(params)}")
        return NoErrors(seed)
    if name == "custom":
        return CustomProfile(seed, **params)
    raise ErrorProfileError(f"unknown error profile {name!r}; known profiles are {list(PROFILE_NAMES)}")


def profile_from_json(data: dict[str, Any]) -> ErrorProfile:
    """Rebuild a profile from :meth:`ErrorProfile.to_json` (composed profiles included)."""
    d = dict(data)
    name = d.pop("name", None)
    if name == "composed":
        return compose(*(profile_from_json(p) for p in d.get("parts", [])))
    if not isinstance(name, str):
        raise ErrorProfileError(f"error profile JSON needs a 'name', got {data!r}")
    return make_profile(name, int(d.pop("seed", 0)), **d)
