"""The shipped dot-pattern images a preset's ``pattern:`` names (package data of the wheel as
ddsgen.pattern_assets; see ``ddsgen.preset.SensorPreset.resolve_path``). Every *.png added here ships."""
