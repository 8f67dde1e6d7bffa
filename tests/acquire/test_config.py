"""Bench and C-arm configurations: the shipped files load, invalid ones are refused naming field and reason."""

from __future__ import annotations

from pathlib import Path

import pytest

from acquire.config import BenchConfig, CArmConfig, load_config, parse_config
from acquire.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name,kind", [("bench.yaml", BenchConfig), ("carm-zeego.yaml", CArmConfig)])
def test_shipped_configs_load(name: str, kind: type) -> None:
    cfg = load_config(ROOT / "config" / name)
    assert isinstance(cfg, kind)
    det = cfg.geometry.detector.panel()
    assert det.rows == 768 and abs(det.pitch_col * det.cols - 427) < 1.0


def test_default_bench_numbers() -> None:
    cfg = load_config(ROOT / "config" / "bench.yaml")
    assert cfg.geometry.sad_mm == 785 and cfg.geometry.sdd_mm == 1200
    assert cfg.stack.order == "stage_on_hexapod"
    small = cfg.with_detector_size(64).geometry.detector.panel()
    assert small.rows == 64 and small.pitch_col == pytest.approx(427 / 64)


@pytest.mark.parametrize(
    "data,field,reason",
    [
        ({"geometry": {"sdd_mm": 500}}, "geometry", "must exceed sad_mm"),
        ({"geometry": {"sad_mm": -1}}, "geometry.sad_mm", "greater than 0"),
        ({"devices": {"hexapod": "http://x"}}, "devices.hexapod", "scheme must be one of"),
        ({"limits": {"hexapod": {"u_deg": [10, -10]}}}, "limits.hexapod", "low < high"),
        ({"stack": {"order": "sideways"}}, "stack.order", "stage_on_hexapod"),
        ({"exposure": {"kv": 500}}, "exposure.kv", "less than or equal to 150"),
        ({"motion": {"settle_ms": "soon"}}, "motion.settle_ms", "valid number"),
        ({"colour": "red"}, "colour", "Extra inputs are not permitted"),
        ({"kind": "submarine"}, "", "bench"),
        ({"geometry": {"sdd_mm": float("inf")}}, "geometry.sdd_mm", "finite number"),  # YAML .inf: beyond every SAD
        ({"geometry": {"du_mm": float("nan")}}, "geometry.du_mm", "finite number"),  # unbounded: NaN passed
        # a twin panel never sees a real generator's exposures (it had stalled at the first frame)
        ({"devices": {"xray": "modbus://10.0.0.5:502"}}, "devices", "make both sim:// or neither"),
        ({"devices": {"xray": "sim://other"}}, "devices", "X-ray twin of its world (xray: sim://bench)"),
        ({"sim": {"clutter": "anatomy"}}, "sim", "clutter 'anatomy' is made for phantom C's torso, not phantom 'A'"),
        ({"sim": {"beam": "white"}}, "sim.beam", "'mono' or 'polychromatic'"),
    ],
)
def test_invalid_config_names_field_and_reason(data: dict, field: str, reason: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_config(data, "test.yaml")
    msg = str(info.value)
    assert msg.startswith("test.yaml: invalid configuration")
    assert field in msg and reason in msg


def test_bad_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("geometry: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_config(bad)


def test_a_twin_in_a_real_bench_takes_the_configuration() -> None:
    """A ``sim://`` device in a real bench's configuration (a rehearsal): the configuration's panel size, distances
    and phantom, where its URI leaves them open; real speed; real devices get only driver options."""
    from acquire.rigs.bench import bench_links

    cfg = parse_config(
        {
            "devices": {
                "hexapod": "tcp://10.0.0.7:50000",
                "rotation_stage": "tcp://10.0.0.8:50000",
                "detector": "sim://bench?rows=64",
            },
            "geometry": {"detector": {"rows": 128, "cols": 96}},
            "sim": {"phantom": "B"},
        },
        "t.yaml",
    )
    links = bench_links(cfg, sim=False)
    det = links["detector"].options
    assert det["cols"] == 96 and "rows" not in det  # the URI's rows=64 stays the URI's
    assert det["sad_mm"] == cfg.geometry.sad_mm and det["phantom"] == "B" and "time_scale" not in det
    assert links["xray"].options["prep_s"] == cfg.exposure.prep_ms / 1000.0
    assert links["hexapod"].options == {} and links["hexapod"].uri == "tcp://10.0.0.7:50000"


def test_the_twins_image_the_configured_clutter() -> None:
    from orbitct.phantoms import Phantom

    cfg = parse_config({"sim": {"phantom": "C", "clutter": "anatomy", "seed": 2}}, "test.yaml")
    imaged = cfg.sim.imaged()
    assert isinstance(imaged, Phantom) and any(p.label == "guide wire" for p in imaged.primitives)
    planned = cfg.sim.model_copy(update={"bbs_mm": [(120.0, 0.0, 0.0)]}).imaged()
    assert planned.n_markers == 1 and any(p.label == "guide wire" for p in planned.primitives)
    assert parse_config({}, "test.yaml").sim.imaged() == "A"
