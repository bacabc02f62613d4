"""The 3D viewer (``posecast view``): a live room as a spectator, or a recording with a
timeline, drawn in the browser by viser (see ``docs/guides/viewer.md``).

- :mod:`posecast.view.scene`: floor, room volume and one avatar per user, with
  interpolator ghosts;
- :mod:`posecast.view.live`: the spectator (the bot's receive path) and its page;
- :mod:`posecast.view.timeline`: what a recording shows at any time (no I/O, no clock);
- :mod:`posecast.view.replay`: the replay page and its timeline controls.
"""

__all__: list[str] = []
