"""Hostile scan files: 55 ways to break a valid one. ``inspect``, ``calibrate`` and ``reconstruct`` each answer
with a one-line error naming the file and a non-zero exit wherever the damage matters to them; never a
traceback, never exit 0 on garbage, never an allocation they did not estimate first."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from orbitct_app.cli.main import cli

pytestmark = [pytest.mark.system, pytest.mark.timeout(120)]

INSPECT, CALIBRATE, RECONSTRUCT = "inspect", "calibrate", "reconstruct"
ALL = frozenset({INSPECT, CALIBRATE, RECONSTRUCT})  # inspect refuses what the computations would: "not usable"
COMMANDS = {
    INSPECT: ["inspect"],
    CALIBRATE: ["calibrate", "--accept-poor"],  # garbage must be refused outright, not merely judged poor
    RECONSTRUCT: ["reconstruct", "--algorithm", "fdk", "--geometry", "nominal", "--shape", "8,8,8", "--voxel-mm", "4"],
}
Mutation = Callable[[h5py.File], Any]


def _set_attr(path: str, key: str, value: Any) -> Mutation:
    return lambda f: f[path].attrs.__setitem__(key, value)


def _del(path: str) -> Mutation:
    return lambda f: f.__delitem__(path)


def _del_attr(path: str, key: str) -> Mutation:
    return lambda f: f[path].attrs.__delitem__(key)


def _replace(path: str, make: Callable[[np.ndarray], Any]) -> Mutation:
    def go(f: h5py.File) -> None:
        old = np.asarray(f[path])
        del f[path]
        f[path] = make(old)

    return go


def _frames(change: Callable[[np.ndarray], np.ndarray], dtype: str = "float32") -> Mutation:
    return _replace("frames/data", lambda a: change(a.astype(np.float64)).astype(dtype))


def _vectors(change: Callable[[np.ndarray], np.ndarray], group: str = "geometry/nominal") -> Mutation:
    def go(f: h5py.File) -> None:
        _replace(f"{group}/vectors", change)(f)
        if f"{group}/matrices" in f:
            del f[f"{group}/matrices"]

    return go


def _on_projection(values: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    def change(v: np.ndarray) -> np.ndarray:
        v = v.copy()
        k = int(np.flatnonzero(np.isfinite(v).all(axis=1))[3])
        v[k] = values(v[k])
        return v

    return change


def _frames_as_group(f: h5py.File) -> None:
    del f["frames/data"]
    f["frames"].create_group("data")


def _huge_frames(f: h5py.File) -> None:  # declares 40000 x 40000 frames but stores none of their pixels
    n = f["frames/data"].shape[0]
    del f["frames/data"]
    f["frames"].create_dataset("data", shape=(n, 40000, 40000), dtype="uint16", chunks=(1, 256, 256))
    f["detector"].attrs.update({"rows": 40000, "cols": 40000})


def _external_link(tmp: Path) -> Mutation:
    def go(f: h5py.File) -> None:
        other = tmp / "elsewhere.h5"
        with h5py.File(other, "w") as g:
            g["data"] = np.asarray(f["frames/data"])
        del f["frames/data"]
        f["frames/data"] = h5py.ExternalLink(str(other), "/data")

    return go


def _raw_external(tmp: Path) -> Mutation:
    def go(f: h5py.File) -> None:
        arr = np.asarray(f["frames/data"])
        raw = tmp / "frames.raw"
        raw.write_bytes(arr.tobytes())
        del f["frames/data"]
        f["frames"].create_dataset("data", shape=arr.shape, dtype=arr.dtype, external=[(str(raw), 0, arr.nbytes)])

    return go


def _virtual(tmp: Path) -> Mutation:
    def go(f: h5py.File) -> None:
        arr = np.asarray(f["frames/data"])
        src = tmp / "source.h5"
        with h5py.File(src, "w") as g:
            g["data"] = arr
        layout = h5py.VirtualLayout(shape=arr.shape, dtype=arr.dtype)
        layout[:] = h5py.VirtualSource(str(src), "data", shape=arr.shape)
        del f["frames/data"]
        f["frames"].create_virtual_dataset("data", layout)

    return go


def _soft_link(f: h5py.File) -> None:
    f["elsewhere"] = np.asarray(f["frames/data"])
    del f["frames/data"]
    f["frames/data"] = h5py.SoftLink("/elsewhere")


# name, mutation (a function of the open file, or of the folder for links), commands that must refuse
CASES: list[tuple[str, Any, frozenset[str]]] = [
    ("format-missing", _del_attr("/", "format"), ALL),
    ("format-wrong", _set_attr("/", "format", "nexus.tomo"), ALL),
    ("format-number", _set_attr("/", "format", 7), ALL),
    ("version-missing", _del_attr("/", "version"), ALL),
    ("version-future", _set_attr("/", "version", 2), ALL),
    ("version-text", _set_attr("/", "version", "one"), ALL),
    ("status-unknown", _set_attr("/", "status", "finished?"), ALL),
    ("status-number", _set_attr("/", "status", 3), ALL),
    ("detector-missing", _del("detector"), ALL),
    ("rows-missing", _del_attr("detector", "rows"), ALL),
    ("rows-zero", _set_attr("detector", "rows", 0), ALL),
    ("rows-negative", _set_attr("detector", "rows", -64), ALL),
    ("rows-text", _set_attr("detector", "rows", "sixty-four"), ALL),
    ("pitch-one-number", _set_attr("detector", "pitch_mm", [0.5]), ALL),
    ("pitch-nan", _set_attr("detector", "pitch_mm", [np.nan, 0.5]), ALL),
    ("pitch-text", _set_attr("detector", "pitch_mm", "0.5 mm"), ALL),
    ("pitch-negative", _set_attr("detector", "pitch_mm", [-0.5, 0.5]), ALL),
    ("frames-missing", _del("frames/data"), ALL),
    ("frames-a-group", _frames_as_group, ALL),
    ("frames-2d", _replace("frames/data", lambda a: a[:, 0, :]), ALL),
    ("frames-wrong-shape", _replace("frames/data", lambda a: a[:, :-3, :]), ALL),
    ("frames-int64", _replace("frames/data", lambda a: a.astype(np.int64)), ALL),
    ("frames-strings", _replace("frames/data", lambda a: np.full(a.shape[:1], b"pixels")), ALL),
    ("frames-huge-declared", _huge_frames, ALL),
    ("image-key-missing", _del("frames/image_key"), ALL),
    (
        "image-key-unknown",
        _replace("frames/image_key", lambda k: np.where(np.arange(k.size) == 5, 7, k).astype("i1")),
        ALL,
    ),
    ("image-key-float", _replace("frames/image_key", lambda k: k.astype(np.float64) + 0.5), ALL),
    ("image-key-short", _replace("frames/image_key", lambda k: k[:-4]), ALL),
    ("time-short", _replace("frames/time_s", lambda t: t[:-4]), ALL),
    ("time-text", _replace("frames/time_s", lambda t: np.full(t.shape, b"soon")), ALL),
    ("nominal-missing", _del("geometry/nominal"), ALL),
    ("nominal-11-columns", _vectors(lambda v: v[:, :11]), ALL),
    ("nominal-short", _vectors(lambda v: v[:-5]), ALL),
    ("nominal-nan", _vectors(_on_projection(lambda r: r * np.nan)), ALL),
    ("nominal-text", _vectors(lambda v: np.full(v.shape[:1], b"geometry")), ALL),
    ("source-on-detector-plane", _vectors(_on_projection(lambda r: np.concatenate([r[3:6], r[3:]]))), ALL),
    ("detector-axes-zero", _vectors(_on_projection(lambda r: np.concatenate([r[:6], np.zeros(6)]))), ALL),
    ("detector-axes-parallel", _vectors(_on_projection(lambda r: np.concatenate([r[:9], r[6:9]]))), ALL),
    ("source-infinite", _vectors(_on_projection(lambda r: np.concatenate([[np.inf, 0, 0], r[3:]]))), ALL),
    ("truth-wrong-shape", _vectors(lambda v: v[:, :6], group="truth/geometry"), ALL),
    ("marker-diameter-nan", _set_attr("markers", "diameter_mm", np.nan), ALL),
    ("marker-diameter-negative", _set_attr("markers", "diameter_mm", -2.0), ALL),
    ("marker-diameter-text", _set_attr("markers", "diameter_mm", "2 mm"), ALL),
    ("frames-all-nan", _frames(lambda a: a * np.nan), ALL),
    ("frames-with-inf", _frames(lambda a: np.where(a > np.median(a), np.inf, a)), ALL),
    ("frames-all-zero", _frames(lambda a: a * 0, "uint16"), ALL),
    ("frames-saturated", _frames(lambda a: a * 0 + 65535, "uint16"), ALL),
    ("frames-negative", _frames(lambda a: -a), ALL),
    ("frames-external-link", "external_link", ALL),
    ("frames-raw-external", "raw_external", ALL),
    ("frames-virtual", "virtual", ALL),
    ("frames-soft-link", _soft_link, frozenset()),  # inside the file: a soft link is ordinary HDF5
]


@pytest.fixture(scope="module")
def valid_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("valid") / "valid.h5"
    r = CliRunner().invoke(
        cli, ["simulate", "--experiment", "A", "--frames", "48", "--detector-size", "192", "--out", str(path)]
    )
    assert r.exit_code == 0, r.output
    check = path.with_name("check.h5")  # the valid file passes every command (run on a copy: results go in)
    shutil.copyfile(path, check)
    for name, args in COMMANDS.items():
        r = CliRunner().invoke(cli, [*args, str(check)])
        assert r.exit_code == 0, (name, r.output)
    return path


def _run(args: list[str], path: Path) -> tuple[int, str]:
    r = CliRunner().invoke(cli, [*args, str(path)])
    crashed = r.exception is not None and not isinstance(r.exception, SystemExit)
    assert not crashed, (args[0], str(path), "".join(__import__("traceback").format_exception(r.exception)))
    return r.exit_code, r.output


@pytest.mark.parametrize("name,mutation,refusers", CASES, ids=[c[0] for c in CASES])
def test_malformed_file(valid_scan: Path, tmp_path: Path, name: str, mutation: Any, refusers: frozenset[str]) -> None:
    path = tmp_path / f"{name}.h5"
    shutil.copyfile(valid_scan, path)
    if isinstance(mutation, str):
        mutation = {"external_link": _external_link, "raw_external": _raw_external, "virtual": _virtual}[mutation](
            tmp_path
        )
    with h5py.File(path, "r+") as f:
        mutation(f)
    for command, args in COMMANDS.items():
        code, out = _run(args, path)
        assert "Traceback" not in out, (command, out)
        if command in refusers:
            assert code != 0, (command, out)
            error_lines = [line for line in out.splitlines() if line.lower().startswith(("error", "usage"))]
            assert error_lines and str(path.name) in error_lines[-1], (command, out)
        else:
            assert code == 0, (command, out)


@pytest.mark.parametrize(
    "content,why",
    [
        (b"", "not a readable HDF5 file"),
        (b"just text, no HDF5 here\n" * 10, "not a readable HDF5 file"),
    ],
    ids=["empty", "text"],
)
def test_files_that_are_not_hdf5(tmp_path: Path, content: bytes, why: str) -> None:
    path = tmp_path / "scan.h5"
    path.write_bytes(content)
    for args in COMMANDS.values():
        code, out = _run(args, path)
        assert code != 0 and why in out and "Traceback" not in out, out


def test_a_corrupted_file_is_refused_in_one_line(valid_scan: Path, tmp_path: Path) -> None:
    path = tmp_path / "corrupt.h5"
    data = bytearray(valid_scan.read_bytes())
    rng = np.random.default_rng(0)
    for at in rng.integers(2048, len(data) // 3, 400):  # scribble over the metadata and early chunks
        data[int(at)] = int(rng.integers(0, 256))
    path.write_bytes(bytes(data))
    for args in COMMANDS.values():
        code, out = _run(args, path)
        assert "Traceback" not in out, out
        if code != 0:
            assert path.name in out.splitlines()[-1], out


def test_an_hdf5_file_that_is_not_a_scan_says_so(tmp_path: Path) -> None:
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["entry/data"] = np.zeros(3)
    code, out = _run(["inspect"], path)
    assert code != 0 and "not an orbitct scan file" in out and "format tag is None" not in out, out


IGNORED = [  # attributes no command needs, as other writers fill them: ignored with a warning, never refused
    ("orbit-json-garbage", _set_attr("orbit", "params_json", "{not json"), "/orbit@params_json is not valid JSON"),
    ("orbit-json-list", _set_attr("orbit", "params_json", "[1, 2]"), "/orbit@params_json is JSON a list"),
    ("phantom-json-garbage", _set_attr("truth", "phantom_json", "phantom?"), "/truth@phantom_json is not valid JSON"),
    (
        "phantom-json-list",
        _set_attr("truth", "phantom_json", '[{"kind": "sphere"}]'),
        "/truth@phantom_json is JSON a list",
    ),
    ("config-json-number", _set_attr("provenance", "config_json", "42"), "/provenance@config_json is JSON a number"),
]


@pytest.mark.parametrize("name,mutation,warning", IGNORED, ids=[c[0] for c in IGNORED])
def test_an_attribute_no_command_needs_is_ignored_with_a_warning(
    valid_scan: Path, tmp_path: Path, name: str, mutation: Any, warning: str
) -> None:
    path = tmp_path / f"{name}.h5"
    shutil.copyfile(valid_scan, path)
    with h5py.File(path, "r+") as f:
        mutation(f)
    for command, args in COMMANDS.items():
        code, out = _run(args, path)
        assert code == 0 and warning in out and "it is ignored" in out, (command, out)


def _damaged(data: bytes) -> dict[str, bytes]:
    """Byte-level damage to a valid scan file: HDF5's own structures (local heaps, B-trees, symbol tables, object
    headers, global heaps) overwritten where their signatures stand, bit flips in the metadata, truncations, a broken
    superblock."""
    out: dict[str, bytes] = {}
    for sig in (b"HEAP", b"TREE", b"SNOD", b"OHDR", b"GCOL"):
        at, found = data.find(sig), 0
        while at >= 0 and found < 3:
            b = bytearray(data)
            b[at + 4 : at + 40] = bytes(x ^ 0xFF for x in b[at + 4 : at + 40])
            out[f"{sig.decode().lower()}-{found}"] = bytes(b)
            at, found = data.find(sig, at + 1), found + 1
    rng = np.random.default_rng(7)
    for seed in range(12):
        b = bytearray(data)
        for at in rng.integers(0, 8192, 16):
            b[int(at)] ^= 1 << int(rng.integers(0, 8))
        out[f"bit-flips-{seed}"] = bytes(b)
    for seed in range(3):  # in the pixels: still a usable file, with odd values
        b = bytearray(data)
        for at in rng.integers(len(data) // 2, len(data), 64):
            b[int(at)] ^= 1 << int(rng.integers(0, 8))
        out[f"pixel-flips-{seed}"] = bytes(b)
    for frac in (0.05, 0.25, 0.5, 0.75, 0.9, 0.999):
        out[f"truncated-{frac}"] = data[: int(len(data) * frac)]
    out["superblock-zeroed"] = bytes(64) + data[64:]
    out["superblock-version"] = data[:8] + bytes([data[8] ^ 0x7F]) + data[9:]
    return out


def _self_link(f: h5py.File) -> None:
    del f["frames/data"]
    f["frames/data"] = h5py.SoftLink("/frames/data")


def _soft_loop(f: h5py.File) -> None:
    f["loop_a"], f["loop_b"] = h5py.SoftLink("/loop_b"), h5py.SoftLink("/loop_a")
    del f["geometry/nominal"]
    f["geometry/nominal"] = h5py.SoftLink("/loop_a")


def _dangling(path: str) -> Mutation:
    def go(f: h5py.File) -> None:
        del f[path]
        f[path] = h5py.SoftLink("/nowhere")

    return go


def _external_missing(f: h5py.File) -> None:
    del f["frames/data"]
    f["frames/data"] = h5py.ExternalLink("/nonexistent/scan.h5", "/frames/data")


def _no_projections(f: h5py.File) -> None:
    key = np.asarray(f["frames/image_key"])
    del f["frames/image_key"]
    f["frames/image_key"] = np.where(key == 0, 3, key).astype("i1")


LINKS: dict[str, Mutation] = {
    "link-to-itself": _self_link,
    "soft-link-loop": _soft_loop,
    "dangling-frames": _dangling("frames/data"),
    "dangling-geometry": _dangling("geometry/nominal/vectors"),
    "dangling-markers": _dangling("truth/markers/xyz"),
    "external-link-missing": _external_missing,
    "no-geometry": _del("geometry"),
    "no-projections": _no_projections,
    "still-acquiring": _set_attr("/", "status", "acquiring"),
    "hard-link-loop": lambda f: f.__setitem__("frames/again", f["frames"]),  # ordinary HDF5: usable
}


def _hostile_files(valid: Path, folder: Path) -> list[Path]:
    files = []
    for name, content in _damaged(valid.read_bytes()).items():
        files.append(folder / f"{name}.h5")
        files[-1].write_bytes(content)
    for name, mutation in LINKS.items():
        files.append(folder / f"{name}.h5")
        shutil.copyfile(valid, files[-1])
        with h5py.File(files[-1], "r+") as f:
            mutation(f)
    return files


def test_damaged_files_are_refused_in_one_sentence_quickly_and_consistently(valid_scan: Path, tmp_path: Path) -> None:
    """At least 40 hostile files: no traceback, each refusal within 2 s naming the file, and inspect agrees with the
    computations (a file it calls usable is reconstructed; one it refuses is refused by calibrate and reconstruct)."""
    import time

    files = _hostile_files(valid_scan, tmp_path)
    assert len(files) >= 40
    refused = 0
    for path in files:
        codes = {}
        for command, args in COMMANDS.items():
            work = path.with_name(f"{path.stem}-{command}.h5")  # each command on its own copy (results go in)
            shutil.copyfile(path, work)
            t = time.monotonic()
            code, out = _run(args, work)
            seconds = time.monotonic() - t
            assert "Traceback" not in out, (path.name, command, out)
            if code != 0:
                last = out.strip().splitlines()[-1]
                assert work.name in last and seconds < 2.0, (path.name, command, round(seconds, 2), out)
            codes[command] = code
        if codes[INSPECT] == 0:
            assert codes[RECONSTRUCT] == 0, (path.name, codes)
        else:
            refused += 1
            assert codes[CALIBRATE] != 0 and codes[RECONSTRUCT] != 0, (path.name, codes)
    assert refused >= 30, refused


def test_a_file_with_only_the_published_contract_is_used(valid_scan: Path, tmp_path: Path) -> None:
    """Another writer's file: only what the published format lists (shared/spec/scan-file.md; none of the
    attributes orbitct added later), and the truth's phantom as a JSON list. Every command uses it."""
    path = tmp_path / "foreign.h5"
    with h5py.File(valid_scan, "r") as src, h5py.File(path, "w") as dst:
        dst.attrs.update({"format": "orbitct.scan", "version": 1, "status": "complete", "status_reason": ""})
        dst.create_group("detector").attrs.update({k: src["detector"].attrs[k] for k in ("rows", "cols", "pitch_mm")})
        for name in (
            "frames/data",
            "frames/image_key",
            "frames/time_s",
            "geometry/nominal/vectors",
            "truth/geometry/vectors",
            "truth/markers/xyz",
        ):
            dst[name] = np.asarray(src[name])
        for group in ("encoders", "commanded"):
            for axis, ds in src[f"frames/{group}"].items():
                dst[f"frames/{group}/{axis}"] = np.asarray(ds)
                dst[f"frames/{group}/{axis}"].attrs["unit"] = ds.attrs.get("unit", "deg")
        dst.create_group("orbit").attrs.update({"name": "sawtooth", "params_json": '{"amplitude_deg": 20}'})
        dst["truth"].attrs["phantom_json"] = '[{"kind": "cylinder", "radius_mm": 80}]'
        dst.create_group("markers").attrs["diameter_mm"] = src["markers"].attrs["diameter_mm"]
    for command, args in COMMANDS.items():
        code, out = _run(args, path)
        assert code == 0 and "Traceback" not in out, (command, out)
        assert "/truth@phantom_json is JSON a list, not an object; it is ignored" in out, (command, out)
