"""Each task's learning side, beside its env (``sonogym.envs.<task>``): ``<task>/agents.py``
holds the task's ``TrainingDefaults``, one config per RL algorithm it trains with (the paper's
tables) and the settings they share on it. The task's ``TaskSpec.agents`` names that module by
entry point, so the simulator imports nothing from here; ``sonogym.agents`` loads it
(``task_defaults.training_defaults``). Plain config dataclasses: no RL library is imported."""
