"""posecast's face: the one CLI, and what composes server, client and experiments.

Nothing imports this package (see DESIGN.md, "Layout").
"""
