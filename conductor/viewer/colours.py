"""A colour per model, the same in Rerun and in Foxglove: fixed for the built-in models, hashed for the rest,
distinct within a run. Nothing here imports a viewer."""
from __future__ import annotations

import zlib
from collections.abc import Iterable

CONDUCTOR = "_conductor"


# Fixed colours for the built-in models, so a scene's physics is always blue and in_hand orange.
FIXED_COLOURS: dict[str, tuple[str, tuple[int, int, int]]] = {
    "physics": ("blue", (52, 120, 246)),
    "in_hand": ("orange", (255, 140, 0)),
    "spu": ("green", (46, 170, 80)),
    "fluid": ("cyan", (0, 190, 210)),
    "grasp_monitor": ("purple", (150, 80, 200)),
}


# Every other model name hashes into this palette (stable across runs; probing avoids a clash
# inside one scene).
PALETTE: tuple[tuple[str, tuple[int, int, int]], ...] = (
    ("red", (220, 50, 47)), ("magenta", (211, 54, 130)), ("yellow", (225, 185, 0)),
    ("brown", (150, 95, 40)), ("pink", (255, 120, 170)), ("olive", (128, 140, 30)),
    ("navy", (40, 60, 150)), ("teal", (0, 128, 128)), ("lime", (140, 210, 40)),
    ("violet", (108, 113, 196)), ("salmon", (250, 128, 114)), ("slate", (100, 120, 140)),
)


GREY = ("grey", (150, 150, 150))


# --------------------------------------------------------------------------- colours
class Colours:
    """Model name → (colour name, RGB): fixed for built-ins, hashed for the rest, distinct per run."""

    def __init__(self, names: Iterable[str] = ()):
        self.assigned: dict[str, tuple[str, tuple[int, int, int]]] = {}
        names = list(dict.fromkeys(names))
        for n in names:  # fixed ones first, so a hashed name never takes their colour
            if n in FIXED_COLOURS:
                self.assigned[n] = FIXED_COLOURS[n]
        for n in sorted(names):
            self.get(n)

    def get(self, name: str) -> tuple[str, tuple[int, int, int]]:
        c = self.assigned.get(name)
        if c is not None:
            return c
        if name == CONDUCTOR or not name:
            c = GREY
        elif name in FIXED_COLOURS and FIXED_COLOURS[name] not in self.assigned.values():
            c = FIXED_COLOURS[name]
        else:
            used = set(self.assigned.values())
            i = zlib.crc32(name.encode()) % len(PALETTE)
            for k in range(len(PALETTE)):
                c = PALETTE[(i + k) % len(PALETTE)]
                if c not in used:
                    break
            else:
                c = PALETTE[i]
        self.assigned[name] = c
        return c

    def rgb(self, name: str) -> tuple[int, int, int]:
        return self.get(name)[1]


def model_colour(name: str) -> tuple[int, int, int]:
    """The colour a model name gets when no other model of its scene claims it first."""
    return Colours([name]).rgb(name)
