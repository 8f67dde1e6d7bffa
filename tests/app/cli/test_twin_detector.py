"""``orbitct twin detector``: the panel twin as a process of its own, following a bench of twins elsewhere."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from acquire.config import load_config
from acquire.rigs.bench import open_bench
from acquire.runner import ScanRequest, ScanRunner
from devices.twins.detector import DetectorTwin
from devices.twins.gcs import start_twin
from devices.twins.runtime import TwinThread
from devices.twins.world import reset_world
from devices.twins.xray import XrayTwin
from orbitct.scanfile import ScanFile
from tests.helpers.service import small_bench_config
from tests.helpers.twin_process import twin_process

pytestmark = [pytest.mark.timeout(180), pytest.mark.system]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", "from orbitct_app.cli.main import main; main()", "twin", "detector", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_a_configuration_whose_bench_lives_in_this_process_is_refused(tmp_path: Path) -> None:
    out = _run("--config", str(small_bench_config(tmp_path)))  # every device sim://
    assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr
    assert "hexapod sim://bench" in out.stderr and "follows tcp:// and modbus:// endpoints only" in out.stderr
    out = _run("--config", str(tmp_path / "missing.yaml"))
    assert out.returncode == 2 and "no such configuration file" in out.stderr and "Traceback" not in out.stderr


def test_a_scan_of_twins_in_other_processes_images_the_object_where_the_axes_were(tmp_path: Path) -> None:
    """Motion and generator twins elsewhere (threads here, on their own sockets), the panel twin a process of its
    own: a scan on the real-bench path (no --sim) records frames that turn with the stage."""
    bench = reset_world("cli-feed")
    threads = [
        start_twin("hexapod", world="cli-feed", time_scale=25.0),
        start_twin("rotation_stage", world="cli-feed", time_scale=25.0),
        TwinThread(XrayTwin(bench, time_scale=25.0)),
    ]
    try:
        path = small_bench_config(tmp_path, size=48)
        data = yaml.safe_load(path.read_text())
        data["devices"] = {
            "hexapod": threads[0].uri,
            "rotation_stage": threads[1].uri,
            "xray": threads[2].uri,
            "detector": "tcp://127.0.0.1:1",
        }  # the panel's own entry: set once it listens
        path.write_text(yaml.safe_dump(data))
        with twin_process("detector", "--config", str(path)) as (port, _):
            data["devices"]["detector"] = f"tcp://127.0.0.1:{port}"
            path.write_text(yaml.safe_dump(data))
            cfg = load_config(path)
            out = tmp_path / "elsewhere.h5"

            async def main() -> None:
                async with open_bench(cfg, sim=False) as rig:
                    await asyncio.gather(rig.hexapod.reference(), rig.stage.reference())
                    res = await ScanRunner(
                        ScanRequest(
                            config=cfg,
                            out=out,
                            orbit="sawtooth",
                            frames=4,
                            errors="none",
                            orbit_params={"amplitude_deg": 20.0},
                            sim=False,
                        ),
                        rig=rig,
                    ).run()
                    assert res.status == "complete", res.reason

            asyncio.run(main())
    finally:
        for t in threads:
            t.stop()
    with ScanFile(out) as sf:
        proj = sf.frames[sf.projection_indices].astype(float)
        flat = sf.frames[np.flatnonzero(sf.image_key == 1)].astype(float).mean(0)
        encoders = {k: v[sf.projection_indices] for k, v in sf.axes("encoders").items()}
    # what a panel imaging the object at each view's read-backs renders (the same twin, in this process)
    world = reset_world("cli-feed-expected")
    twin = DetectorTwin(world, rows=48, sad_mm=cfg.geometry.sad_mm, sdd_mm=cfg.geometry.sdd_mm, phantom=cfg.sim.phantom)
    expected = []
    for k in range(proj.shape[0]):
        world.stage_true_rad = np.radians(encoders["rotation_stage.R"][k])
        pose = np.array([encoders[f"hexapod.{a}"][k] for a in "XYZUVW"])
        world.hexapod_true = np.concatenate([pose[:3], np.radians(pose[3:])])
        ex = cfg.exposure
        expected.append(
            twin.renderer()(
                "projection", twin.true_view(), ex.kv, ex.ma, ex.exposure_ms, np.random.default_rng(k)
            ).astype(float)
        )

    def coarse(image: np.ndarray) -> np.ndarray:  # 8 x 8 px blocks of line integrals: the shadow, not the noise
        return -np.log(image / flat).reshape(6, 8, 6, 8).mean(axis=(1, 3))

    distance = np.array([[np.abs(coarse(p) - coarse(e)).mean() for e in expected] for p in proj])
    assert proj.shape == (4, 48, 48)
    assert (distance.argmin(1) == np.arange(4)).all(), distance.round(4)  # each frame shows its own view
