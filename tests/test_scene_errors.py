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
    assert len(err.problems) == 1, msg  # (each file has one mistake, said once: not again by what depends on it)


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


def test_merge_keys_from_several_maps_or_through_an_alias_are_no_duplicates(tmp_path):
    """Two merge mistakes of the loader (a reviewer's inputs): a map merging several others had its own key called a
    duplicate (the merged pairs were counted as distinct keys), and so had a merging map reached again through an
    alias (its merge keys were resolved in place the first time, so the second time they were plain keys)."""
    head = "clock: {rate: 120}\nmain: physics\ndescription:\n  fast: &fast {kind: ballsim, step: service, rate: 60}\n"
    several = tmp_path / "several.yaml"
    several.write_text(head + "  slow: &slow {kind: gripswitch, step: free, rate: 30}\n"
                              "models:\n  physics: {kind: ballsim}\n  gm: {<<: [*fast, *slow], rate: 20}\n")
    gm = load_scene(several).models["gm"]
    assert (gm.kind, gm.step, gm.rate) == ("ballsim", "service", 20)  # the first map listed wins, as YAML says
    alias = tmp_path / "alias.yaml"
    alias.write_text(head + "models:\n  physics: {kind: ballsim}\n  gm: &gm {<<: *fast, rate: 30}\n  gm2: *gm\n")
    models = load_scene(alias).models
    assert (models["gm"].rate, models["gm2"].rate, models["gm2"].kind) == (30, 30, "ballsim")
    from conductor.scene.load import load_yaml  # a merged 'on' (YAML 1.1's boolean key) given again overrides it
    doc, _ = load_yaml("t: &t {on: {action: x}, do: []}\nu: {<<: *t, on: {action: y}}\n"
                       "w: {<<: [{on: {action: x}}, {on: {action: y}}]}\n", "x.yaml")
    assert doc["u"] == {"on": {"action": "y"}, "do": []} and doc["w"] == {"on": {"action": "x"}}
