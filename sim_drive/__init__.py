"""A simulated servo drive with a two-mass + backlash axis, for CI and demos.

``plant`` is the "real machine" (the product's physics, :mod:`commission.plant`); ``device``
the drive's behaviour around it (CiA 402, waveform player and trace at 8 kHz, limits,
injected faults).
"""
