"""A polychromatic X-ray beam: the tube's spectrum (SpekPy), each material's attenuation against energy (XrayDB),
and what an energy-integrating panel then reads as a line integral, beam hardening included."""

from __future__ import annotations

import math
import threading
from functools import lru_cache

import numba as nb
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from orbitct.phantoms.materials import COMPOSITION, REFERENCE_KEV, mu_of

_LOCK = threading.Lock()  # SpekPy and XrayDB's database are not meant for concurrent first use


@nb.njit(parallel=True, cache=True, nogil=True)
def _harden(li: NDArray[np.float32], ratio: NDArray[np.float64], weight: NDArray[np.float64]) -> NDArray[np.float32]:
    """``-ln sum_e weight[e] exp(-sum_m ratio[m, e] li[m])`` per pixel (0 where no material is crossed)."""
    n_mat, rows, cols = li.shape
    n_e = weight.shape[0]
    out = np.zeros((rows, cols), dtype=np.float32)
    for i in nb.prange(rows):
        crossed = np.empty(n_mat, dtype=np.int64)
        for j in range(cols):
            n = 0
            for m in range(n_mat):
                if li[m, i, j] != 0.0:
                    crossed[n] = m
                    n += 1
            if n == 0:
                continue
            s = 0.0
            for e in range(n_e):
                a = 0.0
                for q in range(n):
                    a += ratio[crossed[q], e] * li[crossed[q], i, j]
                s += weight[e] * math.exp(-a)
            out[i, j] = -math.log(max(s, 1e-30))
    return out


class Beam(BaseModel):
    """A tungsten-anode tube's filtered spectrum seen by a CsI panel (defaults: a C-arm at 90 kV)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    kv: float = Field(90.0, ge=40, le=150, description="tube voltage, kV (the spectrum's highest energy, keV)")
    anode_angle_deg: float = Field(12.0, ge=6, le=20, description="target angle of the anode")
    filter_al_mm: float = Field(3.0, ge=0, le=20, description="aluminium filtration, inherent and added, mm")
    filter_cu_mm: float = Field(0.1, ge=0, le=2, description="added copper filtration, mm")
    csi_mm: float = Field(
        0.6, ge=0.05, le=2, description="CsI scintillator thickness: how much of each energy the panel absorbs"
    )
    bin_kev: float = Field(2.0, ge=0.5, le=5, description="width of the spectrum's energy bins, keV")

    @classmethod
    def preset(cls, name: str) -> Beam | None:
        """A named beam: ``mono`` (None: one energy, the phantom's attenuations as they are) or ``polychromatic``
        (the defaults: 90 kV, 3 mm Al + 0.1 mm Cu, as on a C-arm)."""
        if name == "mono":
            return None
        if name == "polychromatic":
            return cls()
        raise ValueError(f"unknown beam {name!r}; choose from ['mono', 'polychromatic']")

    def at_kv(self, kv: float) -> Beam:
        """The same tube and filters at another voltage (rounded to 1 kV, so spectra are reused)."""
        return self.model_copy(update={"kv": float(round(min(max(kv, 40.0), 150.0)))})

    def spectrum(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Bin energies (keV) and the share of the panel's signal each carries: fluence x energy x absorbed
        fraction in the scintillator, normalised to sum 1."""
        return _spectrum(self.kv, self.anode_angle_deg, self.filter_al_mm, self.filter_cu_mm, self.csi_mm, self.bin_kev)

    def mean_kev(self) -> float:
        """Signal-weighted mean energy (keV)."""
        e, w = self.spectrum()
        return float(e @ w)

    def ratios(self, groups: tuple[tuple[str, str], ...]) -> NDArray[np.float64]:
        """``(groups, bins)``: for each ``(material, displaces)`` group of primitives, its attenuation at each
        bin's energy over that at the reference energy (the phantom's attenuations are given at 60 keV)."""
        e, _ = self.spectrum()
        return np.stack([_group_curve(m, d, tuple(e)) for m, d in groups])

    def harden(self, li_by_group: dict[tuple[str, str], NDArray[np.float32]]) -> NDArray[np.float32]:
        """The line integrals the panel reads, ``-ln(I / I0)``, from each ``(material, displaces)`` group's line
        integrals at the reference energy: every energy attenuated by its own coefficients, summed as the panel
        sums them."""
        groups = tuple(li_by_group)
        stack = np.ascontiguousarray(np.stack([li_by_group[g] for g in groups]), dtype=np.float32)
        _, w = self.spectrum()
        return _harden(stack, self.ratios(groups), w)


@lru_cache(maxsize=64)
def _spectrum(
    kv: float, angle: float, al_mm: float, cu_mm: float, csi_mm: float, bin_kev: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    with _LOCK:
        import spekpy
        import xraydb

        spek = spekpy.Spek(kvp=kv, th=angle, dk=bin_kev)
        if al_mm > 0:
            spek.filter("Al", al_mm)
        if cu_mm > 0:
            spek.filter("Cu", cu_mm)
        e, fluence = spek.get_spectrum()
        e = np.asarray(e, dtype=np.float64)
        absorbed = 1.0 - np.exp(-np.asarray(xraydb.material_mu("CsI", e * 1000.0, density=4.51)) * csi_mm / 10.0)
    w = np.asarray(fluence, dtype=np.float64) * e * absorbed
    keep = w > 1e-6 * w.max()
    e, w = e[keep], w[keep]
    e.setflags(write=False)
    w = w / w.sum()
    w.setflags(write=False)
    return e, w


def _group_curve(material: str, displaces: str, energies_kev: tuple[float, ...]) -> NDArray[np.float64]:
    """A group's attenuation against energy, relative to the reference energy: the material's, less that of the
    material it displaces."""
    if not displaces:
        return _energy_curve(material, energies_kev)
    net = mu_of(material) - mu_of(displaces)
    if abs(net) < 1e-9:
        raise ValueError(f"{material} displacing {displaces} attenuates nothing at {REFERENCE_KEV:g} keV")
    return (
        mu_of(material) * _energy_curve(material, energies_kev)
        - mu_of(displaces) * _energy_curve(displaces, energies_kev)
    ) / net


@lru_cache(maxsize=256)
def _energy_curve(material: str, energies_kev: tuple[float, ...]) -> NDArray[np.float64]:
    if material not in COMPOSITION:
        raise ValueError(
            f"a polychromatic beam needs each primitive's material; {material!r} is not one of {sorted(COMPOSITION)}"
        )
    with _LOCK:
        import xraydb

        e_ev = np.array((*energies_kev, REFERENCE_KEV), dtype=np.float64) * 1000.0
        mass_mu = np.zeros(len(e_ev))
        for element, fraction in COMPOSITION[material].items():
            mass_mu += fraction * np.asarray(xraydb.mu_elam(element, e_ev), dtype=np.float64)
    curve = np.asarray(mass_mu[:-1] / mass_mu[-1], dtype=np.float64)
    curve.setflags(write=False)
    return curve
