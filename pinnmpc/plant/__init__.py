"""The simulated robot the controller drives: scipy's solve_ivp on the model, stick-slip steps, fixed-step
integrators."""

from pinnmpc.plant.base import Plant, PlantError
from pinnmpc.plant.build import make_plant
from pinnmpc.plant.scipy_plant import ScipyPlant

__all__ = ["Plant", "PlantError", "ScipyPlant", "make_plant"]
