"""Agents: the model author's API (:mod:`agents.model`), the runtime that connects a model to an
ensemble (:mod:`agents.runtime`), the built-in models (:mod:`agents.models`) and robot facts
(:mod:`agents.robot`), and the conformance check every model should pass (:func:`agents.testing.check_model`).
``python -m agents KIND --name NAME`` starts one agent."""
from .model import Model, Param, StepWarning, evaluator, service
from .runtime import AgentRuntime, run_agent

__all__ = ["AgentRuntime", "Model", "Param", "StepWarning", "evaluator", "run_agent", "service"]
