"""Property test: whatever a scene file holds, loading it either works or raises a SceneError whose every
problem names the file (never a TypeError, KeyError, RecursionError... from deep inside the loader).

Mutants are made from the shipped scenes: one value anywhere in the tree is replaced by another YAML value
(of any type, including NaN, infinities, huge integers, nested containers), or a key is deleted, or an
expression is garbled; the result is dumped back to YAML and parsed. The seeds are read with the scene
loader, not ``yaml.safe_load``, which would turn every trigger's ``on:`` key into ``True``."""
from __future__ import annotations

import math
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conductor.scene import parse_scene
from conductor.scene.load import load_yaml
from protocol.errors import SceneError

ROOT = Path(__file__).resolve().parent.parent
SEEDS = sorted(ROOT.glob("scenes/*.yaml")) + [ROOT / "tests" / "core_scene.yaml"]
DATA = [load_yaml(p.read_text(), str(p))[0] for p in SEEDS]

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(10**30), max_value=10**30),
    st.sampled_from([10**400, -1, 0, 0.0, -0.0, math.nan, math.inf, -math.inf, 1e308]),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20),
    st.sampled_from(["", "_x", "a.b", "physics", "ball", "pose", "(", "1 +", "closest(", "x" * 3000,
                     "((((((((((((((((((((1))))))))))))))))))))", "not not not", "[1, 2", "'unterminated"]),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.one_of(st.text(max_size=8), st.integers()),
                                                                       inner, max_size=4)), max_leaves=12)


def _paths(node, path=()):
    yield path
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, path + (i,))


def _mutate(data, path, new, delete):
    if not path:
        return new
    parent = data
    for p in path[:-1]:
        parent = parent[p]
    if delete and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = new
    return data


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.integers(min_value=0, max_value=len(SEEDS) - 1), pick=st.integers(min_value=0), new=values,
       delete=st.booleans())
def test_any_mutated_scene_loads_or_raises_a_scene_error(which, pick, new, delete):
    data = yaml.safe_load(yaml.safe_dump(DATA[which]))  # a fresh deep copy
    paths = list(_paths(data))
    mutant = _mutate(data, paths[pick % len(paths)], new, delete)
    try:
        text = yaml.safe_dump(mutant, allow_unicode=True, width=10**6)
    except yaml.YAMLError:
        return
    name = str(SEEDS[which].parent / "mutant.yaml")  # beside its seed: relative unit paths resolve as they do there
    try:
        parse_scene(text, name)
    except SceneError as e:
        assert e.problems and all(str(p).startswith(name) and p.problem for p in e.problems), str(e)


def test_seeds_are_valid_scenes():
    for path, data in zip(SEEDS, DATA, strict=True):
        parse_scene(yaml.safe_dump(data, allow_unicode=True, width=10**6), str(path))


def test_deep_nesting_and_alias_bombs_are_scene_errors():
    deep = "models: {m: {kind: k}}\nname: " + "[" * 2000 + "]" * 2000 + "\n"
    # eight levels of ten aliases each would expand into 10^8 values under an allowed key
    bomb = "models: {m: {kind: k}}\ndescription:\n  a: &a [x, x, x, x, x, x, x, x, x, x]\n"
    for prev, cur in zip("abcdefg", "bcdefgh", strict=True):
        bomb += f"  {cur}: &{cur} [" + ", ".join([f"*{prev}"] * 10) + "]\n"
    for text, problem in ((deep, "nested deeper"), (bomb, "more than")):
        try:
            parse_scene(text, "x.yaml")
        except SceneError as e:
            assert str(e).startswith("x.yaml") and problem in e.problem, str(e)
        else:
            raise AssertionError("accepted")
