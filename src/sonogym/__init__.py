"""SonoGym: scalable simulation for robotic ultrasound and ultrasound-guided spine surgery.

Plain PyTorch, batched over environments, CPU or CUDA. See README.md and docs/.
"""

__version__ = "0.1.0"
