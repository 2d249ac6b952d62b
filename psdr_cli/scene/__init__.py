"""The scene: Mitsuba scenes built from an experiment (z-up world), meshes, Mitsuba 3 XML scenes, OBJ
parts, pinhole cameras and the BSDF parameters an optimisation reads."""
