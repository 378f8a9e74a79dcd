"""End-to-end design: reconstruction networks, the training loop with memory-saving replay of the optics,
configs, checkpoints and evaluation. Sits on top of ``raywave.imaging``; never imported by the physics packages.
"""
