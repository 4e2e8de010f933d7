"""Evaluation: what the synthesized motion looks like beside ground truth and other systems.

=================  ==========================================================
``metrics``        jerk, acceleration, speed histograms, BeatAlign, diversity, seams
``baselines``      random, pose-only and audio-only window choices
``common``         the systems, the joints measured, centring
``controls``       Table 2 of Habibie et al.: does each control do what it says
``evaluate``       held-out and new-speech evaluations of every system
``report``         plots, renders and the HTML report
=================  ==========================================================
"""
