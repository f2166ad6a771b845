"""Imitation-learning policies, one folder each (LeRobot's layout): ``<name>/configuration.py``
holds its config (an ``ILConfig``), ``<name>/modeling.py`` its model (an ``ILModel``);
``base.py`` declares that interface and ``registry.py`` lists the policies by name.

Adding a policy: write its folder and add one ``register(PolicySpec(...))`` line to
``registry.py``. Training, the env-side wrapper, evaluation, learning curves and
``sonogym il-train --policy`` then know it.
"""
