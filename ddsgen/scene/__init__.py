"""Scenes: scene lists (YAML), procedural shapes, per-frame sampling of objects and camera poses."""

from ddsgen.scene.sampling import FrameScene, PlacedObject, sample_frame
from ddsgen.scene.scenelist import SceneList, load_scene_list

__all__ = ["FrameScene", "PlacedObject", "SceneList", "load_scene_list", "sample_frame"]
