"""``python -m posecast.cli``: the same as the ``posecast`` script."""

from posecast.cli import main

main()
