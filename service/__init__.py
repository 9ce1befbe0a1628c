"""energyctl service: the pure control core (energy, estimator, controllers, feasibility, plant model)
and, around it, the drivers that add clocks and I/O."""

__version__ = "0.1.0"
