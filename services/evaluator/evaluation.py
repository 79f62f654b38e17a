"""One evaluation of one weights version: deterministic episodes on held-out seeds in the evaluator's
own env, summarised into what the evaluator reports (``EvalReport``) and records (a history line).

Apart from transport, metrics and storage (the shell publishes, counts and appends), but not a pure
core: it steps the simulator through the shared episode rollout. The policy input is
``services.episodes.rollout.policy_input(obs, observation)`` (the voxel ``policy_image`` or the depth
image, as the weights' spec says), the rollout ``services.episodes.rollout.run_episode``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from proto.control import EvalReport
from proto.weights import WeightsBlob
from services.episodes.builder import EpisodeBuilder
from services.episodes.rollout import policy_input, run_episode
from services.episodes.scores import EpisodeResult, EvalSummary, episode_result, summarize
from services.evaluator.video import Film
from services.tasks import ManipulationEnv, Observation


@dataclass(frozen=True)
class Evaluation:
    """A finished evaluation of one version, pulled when the learner was at ``env_steps``."""

    version: int
    run_id: str
    task: str
    evaluator_id: str
    env_steps: int
    """The learner's env steps when the version was pulled (-1: no gate seen)."""
    at_budget: bool
    results: tuple[EpisodeResult, ...]
    summary: EvalSummary
    wall_seconds: float
    created_at: float
    """Wall clock when the evaluation started."""

    def report(self) -> EvalReport:
        """The message published on EVAL_REPORTS (stamped now)."""
        s = self.summary
        return EvalReport(evaluator_id=self.evaluator_id, run_id=self.run_id, task=self.task,
                          policy_version=self.version, env_steps=self.env_steps, episodes=s.episodes,
                          success_rate=s.success_rate, mean_return=s.mean_return, mean_length=s.mean_length,
                          grasp_score=s.grasp_score, created_at=time.time())  # fmt: skip

    def record(self) -> dict:
        """The line appended to the eval history (with the per-episode seeds, successes, lengths)."""
        s = self.summary
        return {
            "version": self.version,
            "env_steps": self.env_steps,
            "success_rate": s.success_rate,
            "mean_return": s.mean_return,
            "mean_length": s.mean_length,
            "grasp_score": s.grasp_score,
            "episodes": s.episodes,
            "at_budget": self.at_budget,
            "seeds": [r.seed for r in self.results],
            "successes": [r.success for r in self.results],
            "lengths": [r.length for r in self.results],
            "wall_seconds": round(self.wall_seconds, 3),
            "created_at": self.created_at,
            "task": self.task,
            "run_id": self.run_id,
            "evaluator_id": self.evaluator_id,
        }


class EpisodeRunner:
    """Deterministic episodes of a loaded ``PolicyRuntime`` in one env (never a training env).

    ``keep_up(seconds)`` runs between env steps (the shell consumes its subscriptions there and may
    raise to abandon the evaluation); ``on_episode(seconds)`` sees each episode's wall time."""

    def __init__(self, env: ManipulationEnv, task: str, evaluator_id: str,
                 keep_up: Callable[[float], None] | None = None,
                 on_episode: Callable[[float], None] | None = None) -> None:  # fmt: skip
        self.env = env
        self.task = task
        self.evaluator_id = evaluator_id
        self.keep_up = keep_up
        self.on_episode = on_episode

    def episodes(self, runtime, seeds: Sequence[int], film: Film | None = None) -> list[EpisodeResult]:
        """One episode per seed, the recurrent state reset before each; ``film`` films the episodes it
        wants (the scene and the policy's image at every observation; the episodes are the same)."""
        results = []
        for k, seed in enumerate(seeds):
            t0 = time.perf_counter()
            runtime.reset()
            builder = EpisodeBuilder(task=self.task, seed=seed, actor_id=self.evaluator_id,
                                     policy_version=runtime.version, policy_kind="eval", is_demo=False,
                                     segments=self.env.segment_names)  # fmt: skip
            filming = film if film is not None and film.wants(k) else None
            b = run_episode(self.env, seed, self._actor(runtime, filming), builder, self.keep_up,
                            getattr(runtime, "executed", None))  # fmt: skip
            result = episode_result(b.rewards, b.terminated, seed)
            if filming is not None:  # the last observation, which no action answers
                filming.capture(self.env, policy_input(b.obs[-1], runtime.spec.observation))
                filming.cut(k, seed, result.success, float(sum(b.rewards)))
            if self.on_episode is not None:
                self.on_episode(time.perf_counter() - t0)
            results.append(result)
        return results

    def _actor(self, runtime, film: Film | None) -> Callable[[Observation], np.ndarray]:
        observation = runtime.spec.observation

        def act(obs: Observation) -> np.ndarray:
            x = policy_input(obs, observation)
            if film is not None:
                film.capture(self.env, x)
            return runtime.act(x)

        return act

    def evaluate(self, blob: WeightsBlob, runtime, env_steps: int, seeds: Sequence[int],
                 at_budget: bool, film: Film | None = None) -> Evaluation:  # fmt: skip
        """``blob``'s episodes on ``seeds`` in ``runtime`` (loaded from it), summarised (grasp score
        against the env's time limit); ``film``: see ``episodes``."""
        t0, created = time.monotonic(), time.time()
        results = self.episodes(runtime, seeds, film)
        summary = summarize(results, self.env.settings.max_steps)
        return Evaluation(version=blob.version, run_id=blob.run_id, task=self.task,
                          evaluator_id=self.evaluator_id, env_steps=env_steps, at_budget=at_budget,
                          results=tuple(results), summary=summary, wall_seconds=time.monotonic() - t0,
                          created_at=created)  # fmt: skip


__all__ = ["EpisodeRunner", "Evaluation"]
