"""The built-in default scene list: what ``ddsgen render`` draws when no scene list is given.

Two scenes of procedural shapes (:mod:`ddsgen.scene.shapes`) on a table 0.75 m above the floor, seen from tabletop
range: ``tabletop`` (the table in the open, room clutter on the floor around it) and ``against_wall`` (the table
pushed to a wall, a back row of binders, books and a screen along it). Plain data in the schema of
:mod:`ddsgen.scene.scenelist`, which validates it (:func:`~ddsgen.scene.scenelist.load_scene_list` with no path);
``scenes/default.yaml`` mirrors it.
"""

from __future__ import annotations


def default_scene_list_dict() -> dict:
    """The built-in default scene list as plain data (what ``scenes/default.yaml`` mirrors)."""
    pool = [
        {"shape": "box", "size": [0.12, 0.08, 0.06], "class": "box", "albedo": [0.3, 0.8]},
        {"shape": "box", "size": [0.2, 0.15, 0.1], "class": "carton", "albedo": [0.4, 0.8]},
        {"shape": "cylinder", "radius": 0.04, "height": 0.12, "class": "can", "albedo": [0.3, 0.9]},
        {"shape": "sphere", "radius": 0.05, "class": "ball", "albedo": [0.3, 0.9]},
        {"shape": "capsule", "radius": 0.03, "height": 0.14, "class": "capsule", "albedo": [0.3, 0.8]},
        {"shape": "cone", "radius": 0.05, "height": 0.12, "class": "cone", "albedo": [0.3, 0.8], "rest": "upright"},
        {"shape": "torus", "major_radius": 0.06, "minor_radius": 0.02, "class": "ring", "albedo": [0.3, 0.8]},
        {"shape": "mug", "radius": 0.04, "height": 0.1, "wall": 0.006, "handle": 0.035, "class": "mug",
         "albedo": [0.4, 0.9], "rest": "upright"},
        {"shape": "l_bracket", "length": 0.14, "width": 0.06, "height": 0.1, "thickness": 0.015,
         "class": "bracket", "albedo": [0.2, 0.7]},
    ]
    # Unlabelled surroundings (ddsgen/scene/distractors.py), dark to light: room clutter on the floor, and a
    # back row of binders, books and a screen along the wall.
    floor_clutter = [
        {"shape": "box", "size": [0.6, 0.4, 0.3], "class": "crate", "albedo": [0.05, 0.8]},
        {"shape": "box", "size": [0.45, 0.35, 0.5], "class": "carton", "albedo": [0.05, 0.8]},
        {"shape": "box", "size": [0.9, 0.45, 0.4], "class": "cabinet", "albedo": [0.05, 0.8]},
        {"shape": "cylinder", "radius": 0.18, "height": 0.45, "class": "bin", "albedo": [0.05, 0.8]},
        {"shape": "cylinder", "radius": 0.25, "height": 0.6, "class": "drum", "albedo": [0.05, 0.8]},
    ]
    wall_row = [
        {"shape": "box", "size": [0.3, 0.22, 0.1], "class": "books", "albedo": [0.05, 0.8]},
        {"shape": "box", "size": [0.08, 0.28, 0.32], "class": "binder", "albedo": [0.05, 0.8], "rest": "upright"},
        {"shape": "box", "size": [0.55, 0.06, 0.35], "class": "screen", "albedo": [0.05, 0.8], "rest": "upright"},
        {"shape": "box", "size": [0.35, 0.25, 0.3], "class": "carton", "albedo": [0.05, 0.8]},
        {"shape": "box", "size": [0.4, 0.2, 0.2], "class": "file_box", "albedo": [0.05, 0.8]},
        {"shape": "cylinder", "radius": 0.04, "height": 0.22, "class": "bottle", "albedo": [0.05, 0.8],
         "rest": "upright"},
    ]
    return {
        "description": "built-in default: procedural shapes dropped on a table 0.75 m above the floor, camera at"
                       " tabletop range (0.7-1.6 m)",
        "scenes": [
            {
                "name": "tabletop",
                "frames": 4,
                "objects": pool,
                "clutter": {"count": [6, 12], "area": [0.5, 0.5], "min_gap": 0.005},
                "ground": {"size": [1.2, 0.8], "albedo": [0.4, 0.7]},
                "floor": {"depth": 0.75, "size": [6.0, 6.0], "albedo": [0.2, 0.6]},
                "camera": {"distance": [0.7, 1.4], "elevation_deg": [30, 70], "azimuth_deg": [-180, 180],
                           "look_at_jitter": 0.05},
                "distractors": [{"surface": "floor", "count": [4, 8], "area": [5.0, 5.0], "objects": floor_clutter}],
            },
            {
                "name": "against_wall",
                "frames": 4,
                "objects": pool,
                "clutter": {"count": [4, 8], "area": [0.5, 0.35], "min_gap": 0.005},
                "ground": {"size": [1.4, 0.9], "albedo": [0.4, 0.7]},
                "floor": {"depth": 0.75, "size": [6.0, 6.0], "albedo": [0.2, 0.6]},
                "wall": {"distance": 0.45, "width": 4.0, "height": 2.0, "albedo": [0.5, 0.8]},
                "camera": {"distance": [0.8, 1.6], "elevation_deg": [15, 45], "azimuth_deg": [-50, 50],
                           "look_at_jitter": 0.05},
                "distractors": [{"surface": "ground", "count": [4, 7], "area": [1.3, 0.3], "centre": [0.0, 0.3],
                                 "objects": wall_row}],
            },
        ],
    }
