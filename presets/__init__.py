"""The shipped sensor presets, one YAML file each (package data of the wheel as ddsgen.presets; read by name
with ``ddsgen.preset.load_preset``, listed by ``ddsgen presets``). Every *.yaml added here ships."""
