"""Newton's law of cooling as an FMI 2 co-simulation unit (built with pythonfmu at test time): the same law as
``scenes/units/cooling.py`` (FMI 3), so the two FMI versions can be checked against one another."""
import math

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real


class Cooling2(Fmi2Slave):
    author = "twin"
    description = "Newton cooling of a hot drink (FMI 2)"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.temperature_start = 80.0
        self.ambient_temperature = 20.0
        self.tau = 1500.0
        self.temperature = self.temperature_start
        self.register_variable(Real("temperature_start", causality=Fmi2Causality.parameter,
                                    variability=Fmi2Variability.tunable, description="temperature at the start"))
        self.register_variable(Real("ambient_temperature", causality=Fmi2Causality.input,
                                    description="temperature of the surroundings"))
        self.register_variable(Real("tau", causality=Fmi2Causality.parameter, variability=Fmi2Variability.tunable,
                                    description="cooling time constant"))
        self.register_variable(Real("temperature", causality=Fmi2Causality.output,
                                    description="temperature of the drink"))

    def exit_initialization_mode(self):
        self.temperature = self.temperature_start

    def do_step(self, current_time, step_size):
        a = math.exp(-step_size / self.tau)
        self.temperature = self.ambient_temperature + (self.temperature - self.ambient_temperature) * a
        return True
