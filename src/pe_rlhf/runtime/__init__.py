"""The method-neutral runtime: what every method's recipe and learner share, knowing no method.

- the run: :mod:`~pe_rlhf.runtime.run` (a :class:`~pe_rlhf.runtime.run.Learner` plugged into
  :class:`~pe_rlhf.runtime.run.Run`), crash-safe checkpoints (:mod:`~pe_rlhf.runtime.checkpoint`), the batch and
  pending-episode journals (:mod:`~pe_rlhf.runtime.journal`, :mod:`~pe_rlhf.runtime.episode_journal`), the
  collection in progress (:mod:`~pe_rlhf.runtime.collection_state`), one gradient step
  (:mod:`~pe_rlhf.runtime.update`);
- the config: field rules and ``ConfigError`` (:mod:`~pe_rlhf.runtime.config_rules`), the pieces of a structured
  config (:mod:`~pe_rlhf.runtime.config_schema`), Hydra composition (:mod:`~pe_rlhf.runtime.config_compose`), a
  run's saved ``config.yaml`` and the env and mentor checks (:mod:`~pe_rlhf.runtime.config`), the settings an older
  run saved that are no longer settings (:mod:`~pe_rlhf.runtime.config_retired`), the world it
  describes (:mod:`~pe_rlhf.runtime.world`), the recipes' command line (:mod:`~pe_rlhf.runtime.recipe`);
- the outputs: the metrics CSV and loggers (:mod:`~pe_rlhf.runtime.csv_logger`,
  :mod:`~pe_rlhf.runtime.metrics_logger`), learning curves (:mod:`~pe_rlhf.runtime.plots`), the episode GIF
  (:mod:`~pe_rlhf.runtime.video`).

It imports no method: :mod:`pe_rlhf.algorithms` (the registry, the baselines, the proxy-Q learner) sits above it."""
