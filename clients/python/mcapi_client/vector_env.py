"""A Gymnasium vector environment driven by a session group: one member per
sub-environment, the members choosing every sub-environment's action.

    import gymnasium
    from mcapi_client import GrpcClient, models
    from mcapi_client.vector_env import VectorEnvAdapter

    envs = gymnasium.vector.SyncVectorEnv([make_env] * 64)
    with GrpcClient() as mc, mc.create_group(model, 64, seed=7) as agents:
        world = VectorEnvAdapter(envs, agents, stimuli=["food", "water"])
        world.reset(seed=1)
        for _ in range(1000):
            step = world.step()        # envs.step(the members' actions), reported back

For environments with ``Discrete`` observations and actions (a model with
numbered states: the observation is the state, less the space's ``start``)
such as the toy-text ones, whose model :func:`mcapi_client.models.from_gymnasium`
reads from the transition table. ``agents`` is any object with
``VectorAgents``' ``step`` and ``info`` (:class:`~mcapi_client.groups.GroupAgents`):
the gRPC :class:`~mcapi_client.groups.VectorAgents` or the REST
:class:`~mcapi_client.groups.RestVectorAgents`. Needs numpy (the ``vector``
extra); Gymnasium itself is only read, never imported.

**Stimuli.** As :func:`~mcapi_client.models.from_gymnasium`'s continuous
worlds say it: ``stimulus_of(observations, rewards, infos)`` gives each
step's stimuli, here batched: the vector environment's observations (N,),
rewards (N,) and ``infos`` (its dict of arrays) in, an (N, n) array out.
Without ``stimulus_of``, ``stimuli`` names ``info`` keys, one per stimulus
dimension: component j of sub-environment k is ``infos[name][k]`` when
sub-environment k reported it (``infos["_" + name][k]``), else 0. With
neither, one stimulus: the positive part of the reward.

**Episodes end; agents live on.** Gymnasium 1.x's vector environments reset
a sub-environment by default on the ``step`` *after* the one that
terminated or truncated it (``AutoresetMode.NEXT_STEP``): that call ignores
its action and returns the reset observation, reward 0. The adapter keeps
the member and reports it as a move: the member observes the terminal state
(with the stimulus of the step that reached it), then the next episode's
first state with a zero stimulus and its advised action as the action
taken. That is what a model from ``models.from_gymnasium(...,
on_terminated="restart")`` says (a terminal state leads, whatever the
action, to the initial-state distribution), and what a learned model
learns. Other autoreset modes are refused.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ._columns import F64, GroupStep
from .errors import error_for
from .groups import GroupAgents

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = ["VectorStimulusOf", "VectorEnvStep", "VectorEnvAdapter"]

VectorStimulusOf = Callable[[Any, Any, Mapping[str, Any]], Any]
"""``stimulus_of(observations, rewards, infos)``: each sub-environment's
stimulus of a step, an (N, n) array (a vector environment's batched twin of
:data:`mcapi_client.continuous.StimulusOf`)."""


@dataclass(frozen=True)
class VectorEnvStep:
    """One step of every sub-environment, as its member saw it."""

    states: npt.NDArray[np.int64]
    """The state each member was told it is in (N,)."""
    stimuli: npt.NDArray[np.float64]
    """The stimulus each member was told it received (N, n); 0 for a
    sub-environment reset by this step."""
    rewards: npt.NDArray[np.float64]
    """The environment's rewards (N,)."""
    terminated: npt.NDArray[np.bool_]
    truncated: npt.NDArray[np.bool_]
    reset: npt.NDArray[np.bool_]
    """The sub-environments reset by this step (ended by the step before):
    their state is the next episode's first."""
    infos: dict[str, Any]
    """The vector environment's ``infos``."""
    agents: GroupStep
    """The members' reply: their next actions, drives and rewards."""

    @property
    def episode_ended(self) -> npt.NDArray[np.bool_]:
        """The sub-environments whose episode ended on this step (reset by the next)."""
        return np.logical_or(self.terminated, self.truncated)


def _discrete(space: Any, what: str) -> tuple[int, int]:
    """``(n, start)`` of a ``Discrete`` space."""
    if type(space).__name__ != "Discrete":
        raise TypeError(
            f"the sub-environments' {what} space is {space}, not Discrete: "
            "a group of numbered states needs Discrete observations and actions"
        )
    return int(space.n), int(getattr(space, "start", 0))


def _autoreset_mode(envs: Any) -> str:
    mode = (getattr(envs, "metadata", None) or {}).get("autoreset_mode", "NextStep")
    return str(getattr(mode, "value", mode))


class VectorEnvAdapter:
    """Steps a Gymnasium vector environment with a group's actions and
    reports what happened back to the group (see the module's text).

    Args:
        envs: A ``gymnasium.vector.VectorEnv`` (``SyncVectorEnv``,
            ``AsyncVectorEnv``) of N sub-environments with ``Discrete``
            observations and actions, in the default next-step autoreset mode.
        agents: The group's stepping object, N members (``VectorAgents`` or
            ``RestVectorAgents``); member k acts in sub-environment k.
        stimuli: Without ``stimulus_of``: the ``info`` key of each stimulus
            dimension. With it: only the names (their number is checked).
        stimulus_of: ``stimulus_of(observations, rewards, infos)`` -> (N, n).

    Raises:
        TypeError: A space that is not ``Discrete``.
        ValueError: N sub-environments for a group of another size; a
            continuous group; an autoreset mode other than next-step; a
            number of stimulus names that is not the group's.

    Attributes:
        envs, agents: What is stepped.
        actions: The members' current actions (N,), those the next
            :meth:`step` takes.
        returns: Sum of each sub-environment's reward since :meth:`reset` (N,).
        stimulus_totals: Sum of each member's stimuli since :meth:`reset` (N, n).
        episodes: Episodes each sub-environment ended since :meth:`reset` (N,).
        ticks: Steps since :meth:`reset`.
    """

    def __init__(
        self,
        envs: Any,
        agents: GroupAgents,
        *,
        stimuli: Sequence[str] | None = None,
        stimulus_of: VectorStimulusOf | None = None,
    ) -> None:
        info = agents.info
        n_envs = int(envs.num_envs)
        if n_envs != info.size:
            raise ValueError(f"{n_envs} sub-environments for a group of {info.size} members")
        if info.observation_dim:
            raise ValueError("the group's model is continuous; this adapter takes numbered states")
        self.n_states, self._obs_start = _discrete(envs.single_observation_space, "observation")
        self.n_actions, self._action_start = _discrete(envs.single_action_space, "action")
        mode = _autoreset_mode(envs)
        if mode != "NextStep":
            raise ValueError(
                f"the vector environment's autoreset mode is {mode}: the adapter follows "
                "Gymnasium's default, next-step autoreset (AutoresetMode.NEXT_STEP)"
            )
        if stimuli is not None and isinstance(stimuli, str):
            raise TypeError("`stimuli` is a list of names, not one string")
        if stimuli is not None:
            names = tuple(stimuli)
            if len(names) != info.stimuli:
                raise ValueError(
                    f"{len(names)} stimulus names {list(names)} for a group of {info.stimuli} stimuli"
                )
        elif stimulus_of is not None:
            names = tuple(f"stimulus{j}" for j in range(info.stimuli))
        elif info.stimuli == 1:
            names = ("reward",)
        else:
            raise ValueError(
                f"a group of {info.stimuli} stimuli needs `stimuli` (info keys) or `stimulus_of`: "
                "the default stimulus is one number (the positive part of the reward)"
            )
        self.envs = envs
        self.agents = agents
        self.stimuli = names
        self._stimulus_of = stimulus_of
        self._from_info = stimulus_of is None and stimuli is not None
        n = info.size
        self.actions: npt.NDArray[np.uint32] = np.zeros(n, dtype=np.uint32)
        self._resetting = np.zeros(n, dtype=np.bool_)
        self._started = False
        self.returns: npt.NDArray[np.float64] = np.zeros(n)
        self.stimulus_totals: npt.NDArray[np.float64] = np.zeros((n, info.stimuli))
        self.episodes: npt.NDArray[np.int64] = np.zeros(n, dtype=np.int64)
        self.ticks = 0

    def _states(self, observations: Any) -> npt.NDArray[np.int64]:
        states = np.asarray(observations).astype(np.int64, copy=False).reshape(-1) - self._obs_start
        if states.shape != (self.agents.info.size,):
            raise ValueError(f"the vector environment gave observations of shape {np.shape(observations)}")
        return states

    def _stimuli(self, observations: Any, rewards: Any, infos: Mapping[str, Any]) -> npt.NDArray[np.float64]:
        n, width = self.agents.info.size, self.agents.info.stimuli
        if self._stimulus_of is not None:
            out = np.asarray(self._stimulus_of(observations, rewards, infos), dtype=F64)
            if out.shape != (n, width):
                raise ValueError(f"stimulus_of gave shape {out.shape}; ({n}, {width}) expected")
            return out
        if not self._from_info:
            return np.maximum(np.asarray(rewards, dtype=F64), 0.0).reshape(n, 1)
        out = np.zeros((n, width))
        for j, name in enumerate(self.stimuli):
            if name in infos:
                values = np.asarray(infos[name], dtype=F64).reshape(n)
                present = np.asarray(infos.get("_" + name, np.ones(n, dtype=np.bool_)), dtype=np.bool_)
                out[:, j] = np.where(present, values, 0.0)
        return out

    def _advised(self, step: GroupStep) -> GroupStep:
        if step.errors:
            e = step.errors[0]
            raise error_for(e.code, f"member {e.index} (of {len(step.errors)} refused): {e.message}")
        if step.actions.size and int(step.actions.max()) >= self.n_actions:
            raise ValueError(
                f"a member advised action {int(step.actions.max())}; the sub-environments have "
                f"{self.n_actions} (the group's model and the environment disagree)"
            )
        self.actions = step.actions
        return step

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> GroupStep:
        """Resets every sub-environment and the totals, and reports the first
        states to the members; returns their reply (their first actions).

        On a group already stepped (a second :meth:`reset`), the reset is
        reported as the autoreset of every sub-environment: the first states
        with a zero stimulus.

        Raises:
            McapiError: A member's observation was refused (the first of
                them, naming the member); the step of the others stands.
        """
        observations, _infos = self.envs.reset(seed=seed, options=options)
        states = self._states(observations)
        info = self.agents.info
        if self._started:
            step = self.agents.step(states, np.zeros((info.size, info.stimuli)))
        else:
            step = self.agents.step(states)
        self._started = True
        self._resetting[:] = False
        self.returns = np.zeros(info.size)
        self.stimulus_totals = np.zeros((info.size, info.stimuli))
        self.episodes = np.zeros(info.size, dtype=np.int64)
        self.ticks = 0
        return self._advised(step)

    def step(self) -> VectorEnvStep:
        """Steps every sub-environment with its member's action and reports
        the outcome (state, stimulus) to the members.

        Raises:
            RuntimeError: Before :meth:`reset`.
            McapiError: A member's observation was refused (see :meth:`reset`).
            ValueError: ``stimulus_of`` gave the wrong shape, or a member
                advised an action the environment does not have.
        """
        if not self._started:
            raise RuntimeError("call reset() before step()")
        env_actions = self.actions.astype(np.int64) + self._action_start
        observations, rewards, terminated, truncated, infos = self.envs.step(env_actions)
        states = self._states(observations)
        rewards = np.asarray(rewards, dtype=F64)
        stimuli = self._stimuli(observations, rewards, infos)
        reset = self._resetting
        if reset.any():
            stimuli[reset] = 0.0
        agents = self._advised(self.agents.step(states, stimuli))
        terminated = np.asarray(terminated, dtype=np.bool_)
        truncated = np.asarray(truncated, dtype=np.bool_)
        self._resetting = np.logical_or(terminated, truncated)
        self.returns += rewards
        self.stimulus_totals += stimuli
        self.episodes += self._resetting
        self.ticks += 1
        return VectorEnvStep(states, stimuli, rewards, terminated, truncated, reset, dict(infos), agents)
