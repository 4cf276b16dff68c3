"""Thin Cycles renderer: `python -m ragsplat.blender_scenes.render JOB.json` (the venv python with the bpy
module).

The job is a `ragsplat.datagen.job.RenderJob` (its schema and the meaning of each part are there). All
geometry comes ready-made from datagen (one .npz); this module only builds Blender objects and materials, one
per job part, then renders the job's tasks in order in ONE process (persistent data: the scene is synced
once).

Passes: "wet" renders with the water object and the wet-only objects, "dry" without; both 8-bit sRGB PNG,
'Standard' view transform. "depth" renders without water at 1 sample with a 0.01 px pixel filter (exact
surface at the pixel centre) and stores Cycles' z-depth via ragsplat.dataset.layout.write_depth. Every
file is written to a temporary name and renamed, so a killed run never leaves a partial file. The scene
built, and each finished task, print one event line (`ragsplat.datagen.job.Ready`, `Done`) on stdout.
"""

from __future__ import annotations

import json
import math
import struct
import sys
import time
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix, Vector

from ragsplat.datagen.job import (
    Diffuse,
    Done,
    Emission,
    Event,
    Material,
    Ready,
    Refraction,
    RenderJob,
    RenderSettings,
    Ripples,
    Texture,
    Volume,
    event_line,
)
from ragsplat.datagen.spec import LightSpec
from ragsplat.dataset.layout import NO_HIT, write_depth
from ragsplat.outputs import temp_path, write_bytes


def _say(event: Event) -> None:
    print(event_line(event), flush=True)


def _mesh_object(name: str, verts: np.ndarray, tris: np.ndarray, uv: np.ndarray | None) -> bpy.types.Object:
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(verts))
    me.vertices.foreach_set("co", np.ascontiguousarray(verts, dtype=np.float32).ravel())
    me.loops.add(3 * len(tris))
    me.loops.foreach_set("vertex_index", np.ascontiguousarray(tris, dtype=np.int32).ravel())
    me.polygons.add(len(tris))
    me.polygons.foreach_set("loop_start", np.arange(0, 3 * len(tris), 3, dtype=np.int32))
    if uv is not None:
        layer = me.uv_layers.new(name="UVMap")
        layer.data.foreach_set("uv", np.ascontiguousarray(uv[tris.ravel()], dtype=np.float32).ravel())
    me.update(calc_edges=True)
    me.validate()
    obj = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _material(m: Material) -> bpy.types.Material:
    mat = bpy.data.materials.new(m.kind)
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    out = nodes.new("ShaderNodeOutputMaterial")
    match m:
        case Texture():
            tex = nodes.new("ShaderNodeTexImage")
            tex.image = bpy.data.images.load(m.image)
            tex.image.colorspace_settings.name = "sRGB"
            tex.extension = "REPEAT"  # the floor repeats the (periodic) border texture
            tex.interpolation = "Linear"
            bsdf = nodes.new("ShaderNodeBsdfDiffuse")
            bsdf.inputs["Roughness"].default_value = 0.0
            links.new(tex.outputs["Color"], bsdf.inputs["Color"])
            links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        case Emission():
            em = nodes.new("ShaderNodeEmission")
            em.inputs["Strength"].default_value = m.strength
            links.new(em.outputs["Emission"], out.inputs["Surface"])
        case Refraction():
            # Pure refraction, no Fresnel reflection (Glass/Principled would add it). The colour carries the
            # 1/n^2 radiance drop that Cycles does not apply itself (or 1 when the spec switches it off).
            bsdf = nodes.new("ShaderNodeBsdfRefraction")
            bsdf.inputs["IOR"].default_value = m.ior
            bsdf.inputs["Roughness"].default_value = 0.0
            bsdf.inputs["Color"].default_value = (*([m.color] * 3), 1.0)
            surface = bsdf.outputs["BSDF"]
            if m.reflect:
                # A water surface: Fresnel's share R of the light is the mirror image of sky and sun (glint),
                # the rest 1 - R is refracted (with the radiance drop above).
                mirror = nodes.new("ShaderNodeBsdfGlossy")
                mirror.inputs["Roughness"].default_value = 0.0
                fresnel = nodes.new("ShaderNodeFresnel")
                fresnel.inputs["IOR"].default_value = m.ior
                mix = nodes.new("ShaderNodeMixShader")
                links.new(fresnel.outputs["Fac"], mix.inputs["Factor"])
                links.new(bsdf.outputs["BSDF"], mix.inputs[1])
                links.new(mirror.outputs["BSDF"], mix.inputs[2])
                surface = mix.outputs["Shader"]
            links.new(surface, out.inputs["Surface"])
        case Diffuse():
            bsdf = nodes.new("ShaderNodeBsdfDiffuse")
            bsdf.inputs["Color"].default_value = (*([m.color] * 3), 1.0)
            links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
        case Volume():
            # The water body: homogeneous absorption and scattering (1/m per channel) and no surface, so
            # rays cross its boundary unbent; camera, shadow and bounce rays alike are attenuated
            # (Beer-Lambert).
            vol = nodes.new("ShaderNodeVolumeCoefficients")
            vol.inputs["Absorption Coefficients"].default_value = m.absorption
            vol.inputs["Scatter Coefficients"].default_value = m.scattering
            links.new(vol.outputs[0], out.inputs["Volume"])
    return mat


def _world(light: LightSpec | None) -> None:
    world = bpy.data.worlds.new("world")
    bpy.context.scene.world = world
    nodes, links = world.node_tree.nodes, world.node_tree.links
    bg = nodes["Background"]
    if light is None:  # markers-only scenes: nothing but emitters
        bg.inputs["Strength"].default_value = 0.0
        return
    sky = nodes.new("ShaderNodeTexSky")
    sky.sky_type = "PREETHAM"
    elevation, azimuth = math.radians(light.sun_elevation), math.radians(light.sun_azimuth)
    sky.sun_direction = (math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                         math.sin(elevation))
    links.new(sky.outputs["Color"], bg.inputs["Color"])
    bg.inputs["Strength"].default_value = light.sky_strength
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = light.sun_strength
    sun.angle = math.radians(light.sun_angle)
    obj = bpy.data.objects.new("sun", sun)
    obj.rotation_euler = Vector(sky.sun_direction).to_track_quat("Z", "Y").to_euler()  # light shines down -Z
    bpy.context.scene.collection.objects.link(obj)


def _device(scene, wanted: str) -> str:
    """Set Cycles' device; "auto" takes a GPU when one is present. Returns the device used."""
    if wanted in ("GPU", "auto"):
        prefs = bpy.context.preferences.addons["cycles"].preferences
        for backend in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
            try:
                prefs.compute_device_type = backend
            except TypeError:  # backend not compiled into this build
                continue
            prefs.get_devices()
            gpus = [d for d in prefs.devices if d.type == backend]
            if gpus:
                for d in prefs.devices:
                    d.use = d.type == backend
                scene.cycles.device = "GPU"
                return f"GPU ({backend}: {', '.join(d.name for d in gpus)})"
        if wanted == "GPU":
            raise RuntimeError("render device GPU requested but Cycles finds no GPU")
    scene.cycles.device = "CPU"
    return "CPU"


def _setup(job: RenderJob) -> tuple[bpy.types.Scene, bpy.types.Object, list[bpy.types.Object], dict, str]:
    """(scene, camera, the objects hidden outside the wet pass, the geometry's arrays, the device used)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    r, cam, rs = scene.render, job.camera, job.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = cam.width, cam.height, 100
    r.use_persistent_data = True  # sync the (large) bed once, not once per render
    r.use_file_extension = False
    r.film_transparent = False
    r.use_stamp = False
    for prop in r.bl_rna.properties:  # no time or host stamps in the metadata: identical bytes per seed
        if prop.identifier.startswith("use_stamp"):
            setattr(r, prop.identifier, False)
    if rs.threads:
        r.threads_mode, r.threads = "FIXED", rs.threads
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = rs.exposure
    scene.view_settings.gamma = 1.0
    c = scene.cycles
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed, c.use_animated_seed = rs.seed, False
    c.pixel_filter_type = "BLACKMAN_HARRIS"
    # One interreflection between stones; a reflecting water surface needs its one mirror bounce.
    c.max_bounces, c.diffuse_bounces, c.glossy_bounces = 4, 1, job.glossy_bounces
    c.transmission_bounces, c.transparent_max_bounces, c.volume_bounces = 2, 2, 0
    c.caustics_reflective = c.caustics_refractive = False
    c.sample_clamp_direct = c.sample_clamp_indirect = 0.0
    scene.view_layers[0].use_pass_z = True
    device = _device(scene, rs.device)

    geo = dict(np.load(job.geometry))  # decompressed once: the ripples read the water mesh per photo
    wet = []
    for o in job.objects:
        name = o.name
        obj = _mesh_object(name, geo[f"{name}_verts"], geo[f"{name}_tris"], geo.get(f"{name}_uv"))
        obj.data.materials.append(_material(o.material))
        if name == job.water:
            wet.append(obj)
            # Camera rays only: the bed is lit identically with and without water, no caustic paths.
            obj.visible_shadow = obj.visible_diffuse = obj.visible_glossy = False
            obj.visible_transmission = obj.visible_volume_scatter = False
            if job.ripples is not None:
                obj.data.shade_smooth()  # the rippled surface's normals vary smoothly
        else:
            if o.wet_only:
                wet.append(obj)
            obj.data.shade_smooth()
    _world(job.light)

    cd = bpy.data.cameras.new("camera")
    if cam.fx != cam.fy or (cam.cx, cam.cy) != (cam.width / 2, cam.height / 2):
        raise ValueError("only square pixels (fx == fy) and a centred principal point are supported")
    size = max(cam.width, cam.height)
    cd.sensor_fit, cd.sensor_width = "HORIZONTAL" if cam.width >= cam.height else "VERTICAL", 36.0
    cd.sensor_height = 36.0
    cd.lens = cam.fx * 36.0 / size  # focal length in sensor millimetres along the fitted (larger) side
    if cam.fisheye_polynomial:  # a lens with distortion: the sensor's millimetres per pixel as above
        cd.type, cd.panorama_type = "PANO", "FISHEYE_LENS_POLYNOMIAL"
        cd.sensor_width, cd.sensor_height = 36.0 * cam.width / size, 36.0 * cam.height / size
        for k, value in enumerate(cam.fisheye_polynomial):
            setattr(cd, f"fisheye_polynomial_k{k}", value)
    if cam.ortho_scale is not None:  # straight down, the same metres a pixel everywhere
        cd.type, cd.ortho_scale = "ORTHO", cam.ortho_scale
    cd.clip_start, cd.clip_end = 0.01, 1e5
    camera = bpy.data.objects.new("camera", cd)
    scene.collection.objects.link(camera)
    scene.camera = camera
    return scene, camera, wet, geo, device


def _ripple(water: bpy.types.Object, geo, ripples: Ripples, phases: tuple[float, ...]) -> None:
    """Set the water mesh to this photo's surface: z = level (+ sx x + sy y) + weight * ripple height."""
    from ragsplat.datagen.conditions import ripple_height

    verts = geo["water_verts"]
    z = ripples.level + geo["water_weight"] * ripple_height(
        verts[:, :2], np.array(ripples.k), np.array(ripples.amplitude), np.array(phases))
    if ripples.slope is not None:  # the mean surface of a sloping river
        z = z + verts[:, :2] @ np.array(ripples.slope, np.float64)
    co = np.column_stack([verts[:, :2], z]).astype(np.float32)
    water.data.vertices.foreach_set("co", co.ravel())
    water.data.update()


def _configure(scene, wet, kind: str, rs: RenderSettings) -> None:
    for obj in wet:
        obj.hide_render = kind != "wet"
    s = scene.render.image_settings
    if kind == "depth":
        scene.cycles.samples, scene.cycles.filter_width = 1, rs.depth_filter
        s.media_type = "MULTI_LAYER_IMAGE"
        s.file_format, s.color_depth, s.exr_codec = "OPEN_EXR_MULTILAYER", "32", "ZIP"
    else:
        scene.cycles.samples, scene.cycles.filter_width = rs.samples, rs.filter_width
        s.media_type = "IMAGE"
        s.file_format, s.color_mode, s.color_depth, s.compression = "PNG", "RGB", "8", 15


def _depth_from_multilayer(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:  # Blender 5 writes one part per pass
        channels = {k: c for part in f.parts for k, c in part.channels.items()}
    names = [k for k in channels if k.endswith("Depth.Z")]
    if len(names) != 1:
        raise RuntimeError(f"{path}: expected one Depth.Z channel, found {sorted(channels)}")
    depth = np.array(channels[names[0]].pixels, dtype=np.float32)
    depth[~(depth < NO_HIT)] = NO_HIT  # Cycles writes 1e10 for escaped rays; keep exactly one sentinel
    return depth


def _strip_png_text(data: bytes) -> tuple[bytes, dict[str, str]]:
    """The PNG without its text chunks (Cycles stamps its timings there, which would make the bytes differ
    between identical renders), and those texts."""
    keep, text, pos = [data[:8]], {}, 8
    while pos < len(data):
        length = struct.unpack(">I", data[pos:pos + 4])[0]
        chunk = data[pos:pos + 12 + length]
        if chunk[4:8] == b"tEXt":
            key, _, value = chunk[8:8 + length].partition(b"\0")
            text[key.decode("latin-1")] = value.decode("latin-1")
        else:
            keep.append(chunk)
        pos += 12 + length
    return b"".join(keep), text


def _seconds(stamp: str) -> float:
    """Cycles' "[hh:]mm:ss.ff" stamp -> seconds."""
    return sum(float(v) * 60**k for k, v in enumerate(reversed(stamp.split(":"))))


def main(argv: list[str]) -> int:
    t0 = time.perf_counter()
    job = RenderJob.from_json(json.loads(Path(argv[0]).read_text()))
    scene, camera, wet, geo, device = _setup(job)
    _say(Ready(build_s=time.perf_counter() - t0, device=device))
    current = None
    for task in job.tasks:
        t_start = time.perf_counter()
        if task.kind != current:
            current = task.kind
            _configure(scene, wet, current, job.render)
        if task.phases is not None:
            _ripple(bpy.data.objects[job.water], geo, job.ripples, task.phases)
        camera.matrix_world = Matrix(task.c2w_gl)
        out = Path(task.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = temp_path(out).with_suffix(".render")  # Blender's own file; the result is written atomically
        scene.render.filepath = str(tmp)
        t_render = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        t_saved = time.perf_counter()
        if current == "depth":
            write_depth(out, _depth_from_multilayer(tmp))
            cycles_s = None
        else:
            png, stamps = _strip_png_text(tmp.read_bytes())
            cycles_s = sum(_seconds(v) for k, v in stamps.items()
                           if k.endswith((".render_time", ".synchronization_time")))
            write_bytes(out, png)
        tmp.unlink()
        t_end = time.perf_counter()
        _say(Done(name=task.name, kind=current, render_s=t_saved - t_render, cycles_s=cycles_s,
                  total_s=t_end - t_start))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
