"""SonoGym: scalable simulation for robotic ultrasound and ultrasound-guided spine surgery.

Plain PyTorch, batched over environments, CPU or CUDA. ``import sonogym`` registers the tasks
with Gymnasium (``SonoGym/Navigation-v0``, ...). See README.md and docs/.
"""

__version__ = "0.2.0"

from sonogym import envs as _envs  # noqa: E402,F401  (registers the Gymnasium ids)
