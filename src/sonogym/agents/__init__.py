"""RL agents on skrl 2.x (the simulator never imports this package).

* ``adapter``: ``SkrlEnvAdapter``, our torch ``VectorEnv`` as a skrl env (flat observations in
  sorted-key order, ``ObsLayout``, true final observations for time-limit bootstrapping);
* ``networks``: per-task shared-trunk Gaussian policy + value models;
* ``algorithms``: the RL algorithms by name (PPO, A2C, PPO + safety filter, PPO-Lagrangian):
  each one's config, skrl builder and acting hooks; ``register`` adds one;
* ``task_defaults``: the records a task's agents module (``sonogym.tasks.<task>.agents``) is
  made of, and ``training_defaults(task)``;
* ``configs``: a run's resolved config (task defaults, algorithm config, preset, overrides);
* ``train``: ``train(task, algo, ...)`` (TensorBoard, checkpoints, config.json, resume);
* ``checkpoint``: ``load_policy(run_dir)``.
"""
