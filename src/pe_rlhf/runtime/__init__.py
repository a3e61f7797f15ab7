"""The method-neutral runtime: crash-safe checkpoints (:mod:`~pe_rlhf.runtime.checkpoint`) and the one training
run every recipe drives (:mod:`~pe_rlhf.runtime.run`: a :class:`~pe_rlhf.runtime.run.Learner` plugged into
:class:`~pe_rlhf.runtime.run.Run`). It imports no method: ``training``, ``baselines`` and ``algorithms`` sit
above it."""
