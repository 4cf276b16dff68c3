"""The renderer job and its events (`ragsplat.datagen.job`): a preset's job reads back from its JSON as the
same job, and the renderer's event lines parse back into the events it printed."""

import json
import sys
from pathlib import Path

import pytest

from ragsplat.datagen import flight
from ragsplat.datagen.build import _task, passes_for, render_job, run_blender
from ragsplat.datagen.job import Done, Ready, RenderJob, Texture, event_line, material_from_json, parse_event
from ragsplat.datagen.spec import preset, with_slope
from ragsplat.datagen.survey import LENS
from ragsplat.dataset import layout
from ragsplat.errors import RagsplatError


def preset_job(spec, out, lens=None) -> RenderJob:
    """Every pass of every view of `spec` (as `generate` asks for them in an empty directory)."""
    poses = flight.plan(spec)
    if lens:  # the survey's photos through a lens: the wet pass again
        tasks = [_task(spec, "wet", p, layout.output_path(out, "lens", p.name)) for p in poses]
    else:
        tasks = [_task(spec, k, p, layout.output_path(out, k, p.name))
                 for k in passes_for(spec) for p in poses]
    return render_job(spec, out, poses[0].camera, tasks, lens)


@pytest.mark.parametrize("name, lens", [("smoke", None), ("smoke", LENS), ("smoke-field", None),
                                        ("smoke-field-slope", None)])
def test_a_presets_job_reads_back_from_its_json(name, lens, tmp_path):
    spec = with_slope(preset("smoke-field"), 0.01) if name == "smoke-field-slope" else preset(name)
    job = preset_job(spec, tmp_path, lens)
    text = json.dumps(job.to_json())
    assert RenderJob.from_json(json.loads(text)) == job
    views = len(flight.plan(spec))
    assert len(job.tasks) == (views if lens else len(passes_for(spec)) * views)
    d = json.loads(text)
    assert d["render"]["seed"] == spec.seed and d["light"] == vars(spec.light)
    assert d["objects"][0]["material"] == {"kind": "texture", "image": str(tmp_path / "scene" / "albedo.png")}
    assert ("fisheye_polynomial" in d["camera"]) == (lens is not None)
    rippled = spec.conditions is not None
    assert ("ripples" in d) == rippled and any("phases" in t for t in d["tasks"]) == rippled
    if rippled:  # the phases ride on the wet tasks only
        assert all(("phases" in t) == (t["kind"] == "wet") for t in d["tasks"])
        assert ("slope" in d["ripples"]) == spec.water.sloping


def test_job_parts_are_frozen_values():
    job = preset_job(preset("smoke"), Path("out"))
    assert isinstance(job.tasks[0].c2w_gl, tuple) and isinstance(job.tasks[0].c2w_gl[0][0], float)
    with pytest.raises(AttributeError):
        job.tasks[0].kind = "dry"
    assert isinstance(job.objects[0].material, Texture)
    with pytest.raises(RagsplatError, match="unknown material kind 'glass'"):
        material_from_json({"kind": "glass", "ior": 1.5})


def test_events_read_back_from_their_lines():
    events = [Ready(build_s=1.5, device="CPU"),
              Done(name="0007", kind="wet", render_s=2.0, cycles_s=1.75, total_s=2.25),
              Done(name="0007", kind="depth", render_s=0.5, cycles_s=None, total_s=0.75)]
    for e in events:
        line = event_line(e) + "\n"
        assert parse_event(line) == e
        assert json.loads(line.split(" ", 1)[1])["event"] == e.event
    assert parse_event("Fra:1 Mem:12.00M | Synchronizing object | bed\n") is None  # Blender's own log
    for bad in ("@@ragsplat {", '@@ragsplat {"event": "paused"}', '@@ragsplat {"event": "ready"}'):
        with pytest.raises(RagsplatError, match="renderer event not understood"):
            parse_event(bad)


FAKE_RENDERER = """
import json, sys
from pathlib import Path
from ragsplat.datagen.job import Done, Ready, RenderJob, event_line
# as ragsplat.blender_scenes.render reads it
job = RenderJob.from_json(json.loads(Path(sys.argv[-1]).read_text()))
print("Blender 5.0.1 (a line of its own log)")
print(event_line(Ready(build_s=0.25, device="CPU")))
for t in job.tasks:
    print(event_line(Done(name=t.name, kind=t.kind, render_s=1.0, cycles_s=None, total_s=1.5)))
"""


def test_run_blender_hands_the_job_over_and_reads_the_events_back(tmp_path, monkeypatch):
    """`run_blender` with a stand-in for the Blender process (no bpy): the job it writes reads back as the
    renderer reads it, the events come back typed, and Blender's own lines go to the log."""
    fake = tmp_path / "fake_renderer.py"
    fake.write_text(FAKE_RENDERER)
    python = tmp_path / "python"  # run_blender starts `python -m ragsplat.blender_scenes.render JOB`
    python.write_text(f'#!/bin/sh\nexec {sys.executable} {fake} "$@"\n')
    python.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(python))
    job = preset_job(preset("smoke"), tmp_path)
    seen = []
    stats = run_blender(job, tmp_path, seen.append)
    assert stats.images == len(job.tasks) and stats.render_s == len(job.tasks) and stats.device == "CPU"
    assert [(e.name, e.kind) for e in stats.done] == [(t.name, t.kind) for t in job.tasks]
    assert seen[0] == {"event": "done", "name": job.tasks[0].name, "kind": "wet", "render_s": 1.0,
                       "cycles_s": None, "total_s": 1.5}
    assert "a line of its own log" in (tmp_path / "blender.log").read_text()
    assert not list(tmp_path.glob("job.*.json"))  # the job file is tidied up
