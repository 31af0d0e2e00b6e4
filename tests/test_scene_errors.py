"""Broken scene files: each is rejected with a message naming file, line and key.

Each file in tests/scenes/broken/ starts with ``# expect: LINE | KEY`` (KEY may be empty for a
YAML syntax error)."""
from __future__ import annotations

from pathlib import Path

import pytest

from conductor.scene import load_scene
from protocol.errors import SceneError

BROKEN = sorted((Path(__file__).parent / "scenes" / "broken").glob("*.yaml"))


def test_there_are_enough_broken_scenes():
    assert len(BROKEN) >= 15


@pytest.mark.parametrize("path", BROKEN, ids=[p.stem for p in BROKEN])
def test_broken_scene_is_rejected_with_file_line_key(path):
    header = path.read_text().splitlines()[0]
    assert header.startswith("# expect:")
    line, key = [s.strip() for s in header[len("# expect:"):].split("|")]
    with pytest.raises(SceneError) as e:
        load_scene(path)
    err = e.value
    msg = str(err)
    assert err.file == str(path)
    assert err.line == int(line), msg
    assert err.key == key, msg
    assert msg.startswith(f"{path}:{line}: "), msg
    assert err.problem and len(err.problem) > 10


def test_missing_file_is_a_scene_error(tmp_path):
    with pytest.raises(SceneError, match="cannot read scene"):
        load_scene(tmp_path / "nope.yaml")


def test_good_scenes_load():
    for p in sorted((Path(__file__).parent.parent / "scenes").glob("*.yaml")):
        load_scene(p)
    load_scene(Path(__file__).parent / "core_scene.yaml")


def test_yaml_merge_keys_share_settings_and_a_bad_one_is_said(tmp_path):
    """``<<: *anchor`` merges an anchored map's keys, the map's own keys overriding them, as YAML defines; it was
    refused with PyYAML's words about a constructor ("quote it to make it a string", which would not have helped).
    A merge of something that is not a map names its line and key."""
    head = "clock: {rate: 120}\nmain: physics\n"
    good = tmp_path / "merge.yaml"
    good.write_text(head + "models:\n  physics: &fast {kind: ballsim, step: service, rate: 120}\n"
                           "  gm: {<<: *fast, kind: gripswitch, rate: 15}\n")
    scene = load_scene(good)
    assert (scene.models["gm"].kind, scene.models["gm"].rate, scene.models["gm"].step) == ("gripswitch", 15, "service")
    twice = tmp_path / "twice.yaml"
    twice.write_text(head + "models:\n  physics: &fast {kind: ballsim, step: service, rate: 120}\n"
                            "  gm: {<<: *fast, rate: 15, rate: 30}\n")
    with pytest.raises(SceneError, match=r"twice.yaml:5: models.gm.rate: duplicate key 'rate'"):
        load_scene(twice)
    bad = tmp_path / "bad.yaml"
    bad.write_text(head + "models:\n  physics: {<<: [1, 2], kind: ballsim}\n")
    with pytest.raises(SceneError, match=r"bad.yaml:4: models.physics: merge key '<<': expected a mapping"):
        load_scene(bad)
