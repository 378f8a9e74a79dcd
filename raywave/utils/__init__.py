"""Small numerical helpers shared by the physics sub-packages (no plotting, no I/O)."""
