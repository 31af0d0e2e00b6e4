"""Every shipped scene loads and validates (the scene files are part of the product)."""
from __future__ import annotations

from pathlib import Path

import pytest

from conductor.scene import load_scene

SCENES = sorted((Path(__file__).resolve().parent.parent / "scenes").glob("*.yaml"))


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_shipped_scene_loads(path):
    scene = load_scene(path)
    assert scene.main in scene.models
    assert scene.entities
