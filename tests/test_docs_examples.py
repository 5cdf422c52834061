"""The Python examples of README.md and docs/ run against the current code.

Every block must at least compile. The blocks that need no outside file run as written
(in a temporary folder); the sensor page's blocks, which continue each other, run in
page order with small stand-ins for what they assume (a driver dump, a depth map): an
example whose call no longer matches the code fails here, not in a user's hands.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"```python\n(.*?)```", re.S)


def python_blocks(page: Path) -> list[tuple[int, str]]:
    """(first line number, code) of each ```python block of a Markdown page."""
    text = page.read_text()
    return [(text[:match.start()].count("\n") + 2, match.group(1))
            for match in BLOCK.finditer(text)]


def block_containing(page: str, snippet: str) -> str:
    """The one python block of ``page`` (relative to the project) that holds ``snippet``."""
    found = [code for _, code in python_blocks(ROOT / page) if snippet in code]
    assert len(found) == 1, f"{page}: {len(found)} python blocks hold {snippet!r}"
    return found[0]


ALL_BLOCKS = [pytest.param(page, line, code, id=f"{page.name}:{line}")
              for page in PAGES for line, code in python_blocks(page)]


def test_the_pages_have_examples() -> None:
    assert len(ALL_BLOCKS) >= 20


@pytest.mark.parametrize(("page", "line", "code"), ALL_BLOCKS)
def test_every_block_compiles(page: Path, line: int, code: str) -> None:
    compile(code, f"{page.name}:{line}", "exec")


# Blocks that make their own inputs: run as written. (page, a line of the block)
SELF_CONTAINED = [
    ("docs/calibration.md", "write_synthetic_recording(\"rec\", frames, camera)"),
    ("docs/evaluation.md", "register_method_family"),
    ("docs/calibration.md", "calibrate_observations"),
    ("docs/models.md", "twin"),
]


@pytest.mark.parametrize(("page", "snippet"), SELF_CONTAINED,
                         ids=[f"{page}:{snippet[:20]}" for page, snippet in SELF_CONTAINED])
def test_self_contained_blocks_run(page: str, snippet: str, tmp_path: Path,
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from deltar.evaluation import runner

    # The evaluation page registers methods: into copies, so other tests see the
    # registry as it was.
    monkeypatch.setattr(runner, "_METHODS", dict(runner._METHODS))
    monkeypatch.setattr(runner, "_FAMILIES", dict(runner._FAMILIES))
    monkeypatch.chdir(tmp_path)
    exec(compile(block_containing(page, snippet), page, "exec"), {"__name__": "docs_example"})


@pytest.mark.skipif(importlib.util.find_spec("open3d") is None, reason="the map extra")
def test_mapping_block_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from tests.mapping.conftest import write_wall_recording

    write_wall_recording(tmp_path / "rec")  # the recording with poses the block maps
    monkeypatch.chdir(tmp_path)
    code = block_containing("docs/mapping.md", "import")
    exec(compile(code, "docs/mapping.md", "exec"), {"__name__": "docs_example"})
    assert (tmp_path / "map" / "mesh.ply").is_file()


def sensor_page_inputs() -> dict:
    """Stand-ins for what the sensor page's blocks assume, in their units and shapes."""
    import torch

    from deltar.data.procedural import render_scene
    from deltar.sensor import zone_rects

    rng = np.random.default_rng(0)
    scene = render_scene(0)
    rects = zone_rects(scene.intrinsics)
    targets = 3
    detected = rng.integers(1, targets + 1, 64)
    status = np.where(np.arange(targets)[None] < detected[:, None], 5, 255)
    cnh = rng.uniform(-0.05, 0.02, (64, 18))
    cnh[np.arange(64), rng.integers(0, 18, 64)] += 5.0
    status_primary = [5] * 64
    status_primary[3], status_primary[10] = 255, 6
    return {
        # a driver dump: 64 zones, one target each, then T = 3 targets, zone-major
        "distance_mm": rng.uniform(300, 3900, 64).round().tolist(),
        "range_sigma_mm": rng.uniform(5, 40, 64).round(1).tolist(),
        "target_status": status_primary, "t": 12.5, "T": targets,
        "nb": detected.tolist(),
        "multi": (np.sort(rng.uniform(300, 3900, (64, targets)), axis=1).ravel().tolist(),
                  rng.uniform(5, 40, 64 * targets).tolist(), status.ravel().tolist(),
                  np.tile([50.0, 10.0, 10.0], 64).tolist()),
        "depth_np": scene.depth_m, "rects_np": rects,
        "depth_m_batch": torch.from_numpy(np.stack([scene.depth_m, scene.depth_m])),
        "rects_batch": torch.from_numpy(np.stack([rects, rects])),
        "cnh_bin_values": cnh, "nb_targets": [1] * 64,
        "rng": np.random.default_rng(0), "torch_generator": torch.Generator().manual_seed(0),
        "np": np, "torch": torch,
    }


# What each block of the sensor page needs bound before it runs, from the blocks before it.
SENSOR_SETUP = {
    "targets_per_zone=T": "distance_mm, range_sigma_mm, target_status, signal_per_spad = multi",
    "simulate_zones(depth_m, rects)": "depth_m, rects = depth_m_batch, rects_batch",
    "sample_hypotheses(": "mean_m, sigma_m, valid = zones.mean_m, zones.sigma_m, zones.valid\n"
                          "edges_m = torch.linspace(0, 4, 101)\n"
                          "counts = zones.histogram.float()",
    "simulate_cnh(": "distance_mm = np.linspace(300, 3900, 64).tolist()\n"
                     "depth_m, rects = depth_np, rects_np",
    "SignalAugmentation(": "mean, sigma, valid = zones.mean_m, zones.sigma_m, zones.valid",
}


def test_sensor_page_blocks_run_in_order() -> None:
    namespace = sensor_page_inputs()
    blocks = python_blocks(ROOT / "docs" / "sensor.md")
    assert len(blocks) >= 6
    for marker in SENSOR_SETUP:  # each stand-in still reaches the block it is for
        assert sum(marker in code for _, code in blocks) == 1, marker
    for line, code in blocks:
        for marker, setup in SENSOR_SETUP.items():
            if marker in code:
                exec(setup, namespace)
        exec(compile(code, f"sensor.md:{line}", "exec"), namespace)
    # The last blocks' results, as the page describes them.
    frame = namespace["frame"]
    assert frame.hist_counts.shape == (8, 8, 18)
    assert np.allclose(frame.hist_counts.sum(-1)[frame.valid], 1.0, atol=1e-5)
    assert namespace["hist"].shape == (64, 18)
    assert namespace["rects"].shape == (36, 4)
