"""The actor's rollouts of one task, apart from transport (``RolloutActor``): expert, random and
learned episodes with the actor's seeds, what the actor service runs and the demo recorder and tools
reuse. One episode itself is ``services.episodes.rollout.run_episode``."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from services.actor.config import ActorConfig, expert_style
from services.episodes.builder import EpisodeBuilder
from services.episodes.rollout import EpisodeStepper, policy_input, run_episode
from services.tasks import EXPERT_STYLES, ManipulationEnv, make_env
from services.tasks.experts import seed_for_style


class RolloutActor:
    """The actor's loop around an env, separate from transport so tests can drive it directly."""

    def __init__(self, cfg: ActorConfig, instance: str, env: ManipulationEnv | None = None) -> None:
        self.cfg = cfg
        self.instance = instance
        self.env = env or make_env(cfg.task, cfg.env_settings())
        self.counter = 0
        self.stream_seed = -1  # the last seed drawn from this actor's stream: names its episode
        self.prefilled = 0  # env steps of the random prefill done
        self.rng = np.random.default_rng([cfg.seed_base, cfg.index, 17])

    def next_seed(self) -> int:
        seed = self.cfg.first_seed() + self.counter
        self.counter += 1
        self.stream_seed = seed
        return seed

    def builder(self, seed: int, kind: str, version: int, is_demo: bool) -> EpisodeBuilder:
        return EpisodeBuilder(task=self.cfg.task, seed=seed, actor_id=self.instance, policy_version=version,
                              policy_kind=kind, is_demo=is_demo, segments=self.env.segment_names)  # fmt: skip

    def expert_episode(self, k: int, on_step=None) -> EpisodeBuilder:
        """The k-th expert episode. With the observable expert (``cfg.expert``, for the tasks that
        have one) the style comes from the layout: the seed stream is skipped forward to the next
        seed whose layout gives the wanted style (``seed_for_style``), so styles still alternate
        and every run draws the same seeds. The privileged expert takes the next seed as it is."""
        task = self.env.task
        style = expert_style(self.cfg.expert_style, k, getattr(task, "expert_styles", EXPERT_STYLES))
        holder: dict = {}
        if self.cfg.expert == "observable" and hasattr(task, "observable_expert"):
            seed = seed_for_style(self.env, style, iter(self.next_seed, None))

            def act(obs):
                if "expert" not in holder:
                    holder["expert"] = task.observable_expert(self.env)
                return holder["expert"].act(obs)
        else:
            seed = self.next_seed()
            expert_rng = np.random.default_rng([seed, 3])

            def act(_obs):
                if "expert" not in holder:  # built after reset, from the privileged state
                    holder["expert"] = task.expert(self.env, style, expert_rng)
                return holder["expert"].act()

        return run_episode(self.env, seed, act, self.builder(seed, f"expert_{style}", -1, True), on_step)

    def demonstrations(self, n: int, max_attempts: int, on_step=None, stop=None) -> Iterator[EpisodeBuilder]:
        """Expert episodes until ``n`` succeeded, ``max_attempts`` were run or ``stop()`` says so, each
        yielded as it ends, failures included (they do not count towards ``n``; the k-th success is
        ``expert_episode(k)``'s). What the actor publishes first, `mea demos` records and jump starts
        make again, in one order."""
        kept, attempts = 0, 0
        while kept < n and attempts < max_attempts and not (stop is not None and stop()):
            b = self.expert_episode(kept, on_step)
            attempts += 1
            kept += b.success
            yield b

    def random_episode(self, on_step=None) -> EpisodeBuilder:
        """Uniform actions in [-1, 1]^5, or the env's own random action where it has one (the
        surgical task's: a uniformly drawn discrete action)."""
        seed = self.next_seed()
        sample = getattr(self.env, "sample_action", None)
        act = (lambda _o: sample(self.rng)) if sample is not None else (lambda _o: self.rng.uniform(-1, 1, 5))
        return run_episode(self.env, seed, act, self.builder(seed, "random", -1, False), on_step)

    def begin_learned(self, policy, on_step=None) -> EpisodeStepper:
        """A learned episode to step from outside (an actor with several envs batches their policy
        steps): the next seed, the policy's recurrent state started afresh, the env reset."""
        seed = self.next_seed()
        policy.reset()
        builder = self.builder(seed, "learned", policy.version, False)
        return EpisodeStepper(self.env, seed, builder, on_step, getattr(policy, "executed", None))

    def begin_jump_start(self, policy, jump, on_step=None) -> EpisodeStepper:
        """A learned episode on a demonstration's seed (``jump``: a ``jump_start.JumpStart``) whose
        first ``jump.replayed`` steps execute the demonstration's actions, returned at the handover
        (or ended, should the env end it sooner). The policy reads every observation and is told
        every executed action, so its recurrent state at the handover is the one it would have had
        after acting there itself. Its id names a seed drawn from this actor's stream (``episode_id``):
        several envs of one actor jump-starting from the same demonstration get ids of their own."""
        self.next_seed()
        policy.reset()
        builder = self.builder(jump.demo.seed, "jump_start", policy.version, False)
        builder.jump_left = len(jump.demo.actions) - jump.replayed
        episode = EpisodeStepper(
            self.env, jump.demo.seed, builder, on_step, getattr(policy, "executed", None)
        )
        observation = policy.spec.observation
        for action in jump.demo.actions[: jump.replayed]:
            if episode.done:
                break
            t0 = time.perf_counter()
            policy.act(policy_input(episode.obs, observation))  # advances its state; the demo acts
            episode.step(action, t0)
        return episode

    def learned_episode(self, policy, on_step=None) -> EpisodeBuilder:
        """One episode with a ``PolicyRuntime`` (stochastic; its recurrent state starts afresh)."""
        episode, observation = self.begin_learned(policy, on_step), policy.spec.observation
        while not episode.done:
            t0 = time.perf_counter()
            episode.step(policy.act(policy_input(episode.obs, observation)), t0)
        return episode.builder

    def next_is_learned(self) -> bool:
        """Whether ``policy_episode`` runs the learned policy next (the random prefill is done)."""
        return self.cfg.policy == "learned" and self.prefilled >= self.cfg.random_steps

    def policy_episode(self, k: int, policy=None, on_step=None) -> EpisodeBuilder:
        """Episode k after the demonstrations: a random one while the random prefill
        (``random_steps``) is not done, then the configured policy source."""
        if self.prefilled < self.cfg.random_steps:
            b = self.random_episode(on_step)
            self.prefilled += b.num_steps
            return b
        if self.cfg.policy == "expert":
            return self.expert_episode(k, on_step)
        if self.cfg.policy == "learned":
            return self.learned_episode(policy, on_step)
        return self.random_episode(on_step)

    def episode_id(self, b: EpisodeBuilder) -> str:
        """``<instance>-<seed>-<counter>`` of the episode just run: the seed it drew from this actor's
        stream (its env seed, except in a jump start) and how many it drew."""
        return f"{self.instance}-{self.stream_seed}-{self.counter}"
