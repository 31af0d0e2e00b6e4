"""A trivial service-stepped model: the load of the overhead benchmark (it does no work)."""
from ..model import Model


class Trivial(Model):
    kind = "trivial"
    role = "observer"
    wants_telemetry = False

    def step(self, tick, t, dt, telemetry, inputs):
        pass
