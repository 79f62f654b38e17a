"""One episode of a task with any policy: ``run_episode`` rolls it out into an ``EpisodeBuilder``,
``policy_input`` builds a learned policy's input from an observation. Shared by the actor, the
evaluator, `mea robot --sim` and the tools, below all of them; a learned policy's input is built here
exactly as the augmenter attaches it to stored episodes."""

from __future__ import annotations

import time

import numpy as np

from services.episodes.builder import EpisodeBuilder
from services.observation.depth_image import policy_images as depth_policy_images
from services.observation.projection import segment_policy_images
from services.tasks import ManipulationEnv
from services.tasks.env import Observation


def policy_image(obs: Observation) -> np.ndarray:
    """The learned policy's input for one observation: voxel projection + jaw, uint8 (2, 84, 84),
    bit-identical to what the augmenter attaches to stored episodes."""
    return segment_policy_images(obs.points[None], obs.point_counts[None], np.array([obs.jaw], np.float32))[0]


def policy_input(obs: Observation, observation: str) -> np.ndarray:
    """The learned policy's input for ``observation`` ("voxel" or "depth": uint8 (2, 84, 84); "dsa":
    the env's own DSA image, uint8 (3, 64, 64)).

    ``voxel``: ``policy_image(obs)``. ``depth``: the rendered depth image's codes + jaw
    (``services.observation.depth_image.policy_images``), taken through float16 first, as the
    published episode stores it, so the input is bit-identical to what the augmenter attaches for
    the learner. Needs ``obs.depth_image`` (an env with ``depth_image=True``); ValueError otherwise.
    """
    if observation == "voxel":
        return policy_image(obs)
    if observation == "dsa":
        if obs.image is None:
            raise ValueError("a DSA policy needs a task whose env renders the DSA image (surgical_grasp_any)")
        return obs.image
    if observation != "depth":
        raise ValueError(f"observation must be voxel, depth or dsa, not {observation!r}")
    if obs.depth_image is None:
        raise ValueError("a depth policy needs the rendered depth image: start the actor with --depth-image")
    depth = np.asarray(obs.depth_image).astype(np.float16)[None]
    return depth_policy_images(depth, np.array([obs.jaw], np.float32))[0]


class EpisodeStepper:
    """One episode advanced a step at a time: ``run_episode`` loops over it, and an actor with several
    envs steps one per env in lockstep (one batched policy step per tick).

    The env is reset to ``seed`` on construction; ``obs`` is the observation to act on next.
    ``step(action)`` records the action the env reports as executed (``info['executed_action']``)
    where it reports one, tells ``executed`` that action, and returns True once the episode ended.
    ``on_step(seconds)`` sees each step's time: from ``t0`` where the caller gives it (the policy's
    time included), else the env step alone."""

    def __init__(self, env: ManipulationEnv, seed: int, builder: EpisodeBuilder, on_step=None, executed=None):
        self.env, self.builder, self.on_step, self.executed = env, builder, on_step, executed
        self.obs = env.reset(seed)
        builder.meta["fixed_object"] = env.task.fixed_index()  # privileged, for the learner's critic
        conditions = getattr(env, "episode_conditions", None)  # what the env drew besides the seed
        if conditions is not None:
            builder.meta["conditions"] = conditions()
        builder.observe(self.obs)
        self.done = False

    def step(self, action: np.ndarray, t0: float | None = None) -> bool:
        if self.done:
            raise RuntimeError("the episode has ended")
        t0 = time.perf_counter() if t0 is None else t0
        self.obs, reward, terminated, truncated, info = self.env.step(action)
        if self.on_step is not None:
            self.on_step(time.perf_counter() - t0)
        self.builder.observe(self.obs)
        done = info.get("executed_action", action)
        if self.executed is not None:
            self.executed(done)
        self.builder.step(done, reward, terminated, truncated)
        self.done = bool(terminated or truncated) or self.builder.num_steps >= self.env.settings.max_steps
        return self.done


def run_episode(
    env: ManipulationEnv, seed: int, act, builder: EpisodeBuilder, on_step=None, executed=None
) -> EpisodeBuilder:
    """Roll out one episode with ``act(obs) -> action`` (``EpisodeStepper``); ``on_step(seconds)`` sees
    each step's time, the policy's included. In ``surgical_grasp_any`` the hybrid controller's approach
    replaces the policy's action in the record; ``executed(action)``, if given, is told that action
    after every step (a policy whose state follows what was executed: ``PolicyRuntime.executed``)."""
    episode = EpisodeStepper(env, seed, builder, on_step, executed)
    while not episode.done:
        t0 = time.perf_counter()
        episode.step(act(episode.obs), t0)
    return builder
