"""The scene frame: which way is up and how many metres a capture unit is, decided once before
observation (``resolve``), recorded in the manifest's ``frame`` section and applied to the
whole capture; every later stage works in that metric, +z-up world."""
