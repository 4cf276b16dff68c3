"""How datagen talks to the Blender process (no bpy here: both sides import it).

The renderer prints one line per event on stdout, `PROTOCOL` followed by a JSON object: {"event": "ready",
"build_s", "device"} once the scene is built, then {"event": "done", "name", "kind", "render_s",
"cycles_s", "total_s"} per finished image. Every other line is Blender's own log.
"""

PROTOCOL = "@@ragsplat "
