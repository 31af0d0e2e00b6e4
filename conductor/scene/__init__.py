"""Scenes: load a scene file with the line of every key, check it alone and against the agents' declarations,
and hand the conductor a :class:`Scene`."""
from .check import check_against_agents, check_launchable, launch_problems, load_scene, parse_scene, reads_of
from .perception import check_perception
from .spec import Effect, EntitySpec, EvaluatorSpec, ModelSpec, Scene, TriggerSpec

__all__ = ["Effect", "EntitySpec", "EvaluatorSpec", "ModelSpec", "Scene", "TriggerSpec", "check_against_agents",
           "check_launchable", "check_perception", "launch_problems", "load_scene", "parse_scene", "reads_of"]
