"""How ``sonogym demo`` shows reconstruction (``TaskSpec.demo`` of
``sonogym.envs.reconstruction``): the reconstruction so far, projected over elevation, beside a
top-down view of the back with the probe's path."""

from sonogym.envs import frames
from sonogym.tasks.demo import Demo

DEMO = Demo(
    image=frames.reconstruction_image, frame=frames.probe_frame, point=frames.probe_position
)
