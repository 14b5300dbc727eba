"""CM2 simulator: scenes, objects and effects."""
