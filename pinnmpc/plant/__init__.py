"""The simulated robot the controller drives: scipy's solve_ivp on the model, stick-slip steps, fixed-step
integrators."""

from pinnmpc.plant.scipy_plant import PlantError, ScipyPlant

__all__ = ["PlantError", "ScipyPlant"]
