"""Files: EXR and PNG images, the JSON Lines manifest, atomic writes, scan-folder readers."""
