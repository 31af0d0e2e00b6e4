"""Newton's law of cooling as an FMI 3 co-simulation unit (the fmu model builds it with pythonfmu3 on first use).

dT/dt = -(T - T_ambient) / tau: a drink at temperature T in surroundings at T_ambient loses heat in proportion
to the difference; tau is the time constant of its container (a ceramic mug of coffee: about 25 minutes, an
open spill on a table: a couple of minutes). The output ``temperature`` is an attribute the twin's fmu model
can own; ``temperature_start`` is where a handed-over temperature restarts the unit. Stepped with the exact
solution of the linear equation, so any step size is stable.
"""
import math

from pythonfmu3 import Float64, Fmi3Causality, Fmi3Slave, Fmi3Variability
from pythonfmu3.unit import Unit


class Cooling(Fmi3Slave):
    author = "twin"
    description = "Newton cooling of a hot drink"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.time = 0.0
        self.temperature_start = 80.0
        self.ambient_temperature = 20.0
        self.tau = 1500.0
        self.temperature = self.temperature_start
        self.register_units([Unit("degC", K=1, offset=273.15), Unit("s", s=1)])
        self.register_variable(Float64("time", causality=Fmi3Causality.independent,
                                       variability=Fmi3Variability.continuous))
        self.register_variable(Float64("temperature_start", causality=Fmi3Causality.parameter,
                                       variability=Fmi3Variability.tunable, start=80.0, unit="degC",
                                       description="temperature of the drink at the start"))
        self.register_variable(Float64("ambient_temperature", causality=Fmi3Causality.input, start=20.0,
                                       unit="degC", description="temperature of the surroundings"))
        self.register_variable(Float64("tau", causality=Fmi3Causality.parameter, variability=Fmi3Variability.tunable,
                                       start=1500.0, unit="s", description="cooling time constant of the container"))
        self.register_variable(Float64("temperature", causality=Fmi3Causality.output, unit="degC",
                                       description="temperature of the drink"))

    def exit_initialization_mode(self):
        self.temperature = self.temperature_start

    def do_step(self, current_time, step_size):
        a = math.exp(-step_size / self.tau)
        self.temperature = self.ambient_temperature + (self.temperature - self.ambient_temperature) * a
        self.time = current_time + step_size
        return True
