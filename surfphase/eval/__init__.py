"""Evaluation of a session's reconstruction: image metrics on held-out views, Chamfer
distance to true meshes, bubble velocity error, the classical two-view baseline and the
2D reference for sessions without ground truth.

Ground truth is read from files (never from :mod:`surfphase.synth`).
"""
