"""The evaluator's Prometheus metrics (``mea_evaluator_*``): evaluations, success rate, grasp score,
episode timings and refused weights."""

from __future__ import annotations

from services.common.metrics import ServiceMetrics

_SECONDS = (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 60.0)


def evaluator_metrics(m: ServiceMetrics) -> dict:
    return {
        "evaluations": m.counter("mea_evaluator_evaluations", "Evaluations finished and reported."),
        "success_rate": m.gauge("mea_evaluator_success_rate", "Success rate of the last evaluation."),
        "mean_return": m.gauge("mea_evaluator_mean_return", "Mean return of the last evaluation."),
        "mean_length": m.gauge("mea_evaluator_mean_length", "Mean episode length (steps), last evaluation."),
        "grasp_score": m.gauge("mea_evaluator_grasp_score", "Mean grasp score s_g of the last evaluation."),
        "version": m.gauge(
            "mea_evaluator_policy_version", "Weights version of the last evaluation (-1: none)."
        ),
        "env_steps": m.gauge(
            "mea_evaluator_env_steps",
            "Learner env steps when the last evaluated version was pulled (-1: unknown).",
        ),
        "improvement": m.gauge(
            "mea_evaluator_improvement_env_steps",
            "Improvement timestep so far: env steps from which every evaluation had success > 0 (-1: none).",
        ),
        "episode_seconds": m.histogram(
            "mea_evaluator_episode_seconds", "Wall time of one evaluation episode.", _SECONDS
        ),
        "bad_weights": m.counter(
            "mea_evaluator_bad_weights",
            "Weights versions skipped, by reason (load: do not fit; observation: no depth image here).",
            ["reason"],
        ),
    }
