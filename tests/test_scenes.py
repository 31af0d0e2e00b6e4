"""Every shipped scene loads and validates (the scene files are part of the product), survives being written
out again in another YAML style, and fits the agents of the kinds it names."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from agents.registry import resolve_kind
from conductor.scene import Scene, check_against_agents, load_scene, parse_scene
from conductor.scene.load import Lines

ROOT = Path(__file__).resolve().parent.parent
SCENES = sorted((ROOT / "scenes").glob("*.yaml"))
# every scene something runs: the shipped ones and those of the tests
RUNNABLE = SCENES + sorted((ROOT / "tests" / "scenes").glob("*.yaml")) + [ROOT / "tests" / "core_scene.yaml"]


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_shipped_scene_loads(path):
    scene = load_scene(path)
    assert scene.main in scene.models
    assert scene.entities


def _unlined(scene: Scene) -> Scene:
    """The scene without its line numbers (a file written in another style has its keys on other lines)."""
    models = {n: dataclasses.replace(m, line=None) for n, m in scene.models.items()}
    triggers = [dataclasses.replace(t, line=None, do=[dataclasses.replace(e, line=None) for e in t.do])
                for t in scene.triggers]
    return dataclasses.replace(scene, models=models, triggers=triggers, lines=Lines())


@settings(max_examples=80, deadline=None)
@given(path=st.sampled_from(RUNNABLE), flow=st.sampled_from([None, True, False]), indent=st.integers(2, 9),
       width=st.integers(20, 400), canonical=st.booleans(), explicit_start=st.booleans())
def test_a_scene_written_out_again_loads_unchanged(path, flow, indent, width, canonical, explicit_start):
    scene = load_scene(path)
    text = yaml.safe_dump(scene.raw, default_flow_style=flow, indent=indent, width=width, canonical=canonical,
                          explicit_start=explicit_start, sort_keys=False, allow_unicode=True)
    again = parse_scene(text, scene.file)
    assert _unlined(again) == _unlined(scene)
    assert list(again.models) == list(scene.models)  # the order of the models is part of the scene
    assert again.raw == scene.raw == load_scene(path).raw  # and checking it changed nothing it was given


def _register(name: str, kind: str) -> dict[str, Any]:
    """What an agent of ``kind`` declares when it registers as ``name`` (agents/runtime.py, descriptor)."""
    cls = resolve_kind(kind)
    return {"name": name, "kind": cls.kind, "role": cls.role, "step_modes": list(cls.step_modes),
            "params": {k: p.describe() for k, p in cls.params.items()}, "attributes": list(cls.attributes),
            "outputs": list(cls.outputs), "events": list(cls.events), "evaluators": sorted(cls.evaluators()),
            "services": sorted(cls.services()), "reads": list(cls.reads)}


@pytest.mark.parametrize("path", RUNNABLE, ids=[p.stem for p in RUNNABLE])
def test_a_runnable_scene_fits_the_agents_of_its_kinds(path):
    scene = load_scene(path)
    agents = {name: _register(name, spec.kind) for name, spec in scene.models.items()}
    assert [str(p) for p in check_against_agents(scene, agents)] == []
