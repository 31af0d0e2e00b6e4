"""A trivial mosaik 3 simulator (one process each) for the overhead comparison: steps, does nothing."""
import mosaik_api_v3

META = {"api_version": "3.0", "type": "time-based",
        "models": {"Model": {"public": True, "params": [], "attrs": ["val"]}}}


class Trivial(mosaik_api_v3.Simulator):
    def __init__(self):
        super().__init__(META)

    def init(self, sid, time_resolution=1.0, **kw):
        return self.meta

    def create(self, num, model, **kw):
        return [{"eid": f"m{i}", "type": model} for i in range(num)]

    def step(self, time, inputs, max_advance):
        return time + 1

    def get_data(self, outputs):
        return {}


if __name__ == "__main__":
    mosaik_api_v3.start_simulation(Trivial())
