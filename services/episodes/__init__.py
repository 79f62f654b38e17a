"""Episodes, below the services that share them: build one (``builder``), roll one out with any
policy (``rollout``), score one (``scores``). The actor, the evaluator, `mea robot --sim` and the
tools all run episodes through here, so no service package imports another's episode code."""
