"""RL agents on skrl 2.x (the simulator never imports this package).

* ``adapter``: ``SkrlEnvAdapter``, our torch ``VectorEnv`` as a skrl env (flat observations in
  sorted-key order, ``ObsLayout``, true final observations for time-limit bootstrapping);
* ``networks``: per-task shared-trunk Gaussian policy + value models;
* ``configs``: the paper's per-task PPO / A2C hyperparameters and the skrl agent factory;
* ``train``: ``train(task, algo, ...)`` (TensorBoard, checkpoints, config.json, resume);
* ``checkpoint``: ``load_policy(run_dir)``.
"""
