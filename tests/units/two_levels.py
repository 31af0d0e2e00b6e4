"""Two levels that fall at 1 per second as an FMI 3 co-simulation unit (built with pythonfmu3 at test time), with an
Int64 parameter: ``fail_after`` steps, if above 0, after which a step fails (as a solver that gives up does)."""
from pythonfmu3 import Float64, Fmi3Causality, Fmi3Slave, Fmi3Variability, Int64


class TwoLevels(Fmi3Slave):
    author = "twin"
    description = "two levels falling at 1/s; a step fails after fail_after steps"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.time = 0.0
        self.a_start, self.b_start, self.a, self.b = 10.0, 10.0, 10.0, 10.0
        self.fail_after, self.steps = 0, 0
        self.register_variable(Float64("time", causality=Fmi3Causality.independent,
                                       variability=Fmi3Variability.continuous))
        for name in ("a_start", "b_start"):
            self.register_variable(Float64(name, causality=Fmi3Causality.parameter,
                                           variability=Fmi3Variability.tunable, start=10.0))
        self.register_variable(Int64("fail_after", causality=Fmi3Causality.parameter,
                                     variability=Fmi3Variability.tunable, start=0))
        self.register_variable(Float64("a", causality=Fmi3Causality.output))
        self.register_variable(Float64("b", causality=Fmi3Causality.output))

    def exit_initialization_mode(self):
        self.a, self.b, self.steps = self.a_start, self.b_start, 0

    def do_step(self, current_time, step_size):
        self.steps += 1
        self.a -= step_size
        self.b -= step_size
        return not (self.fail_after > 0 and self.steps > self.fail_after)
