"""The files of an `ambhil run`: ``<run-id>.mcap`` (the recorder's) and ``<run-id>.rrd`` (converted
from it at the end), how an unfinished recording is restored, what the summary reads back from
the recording, and how a failed run's files are marked (``.failed.mcap`` / ``.failed.rrd``).

The recording's readers (mcap, rerun, zenoh through replay) are imported inside the functions:
`ambhil --help` stays quick."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def run_files(outdir: Path, run_id: str) -> tuple[Path, Path]:
    """(``<run-id>.mcap``, ``<run-id>.rrd``) in ``outdir`` (created); a rerun of the same id
    leaves no ``.failed`` marker of an older run."""
    outdir.mkdir(parents=True, exist_ok=True)
    for stale in (outdir / f"{run_id}.failed.mcap", outdir / f"{run_id}.failed.rrd"):
        stale.unlink(missing_ok=True)
    return outdir / f"{run_id}.mcap", outdir / f"{run_id}.rrd"


def restore_unfinished(mcap: Path) -> None:
    """A recorder that gave no summary or could not write: copy the readable part of its file
    into a complete MCAP in its place (bridge/recording/recover.py), or say why not."""
    from ambhil.bridge.recording.recover import RecordingError, recover
    fixed = mcap.with_suffix(".recovered.mcap")
    try:
        k = recover(str(mcap), str(fixed))
        fixed.replace(mcap)
        print(f"ambhil run: recorder did not finish {mcap}; recovered {k} messages into it", file=sys.stderr)
    except (OSError, RecordingError) as e:
        fixed.unlink(missing_ok=True)
        print(f"ambhil run: recorder did not finish {mcap}, and its readable part could not be copied "
              f"({e}); the file is kept as it is (`ambhil recover` it where there is room)", file=sys.stderr)


def write_rrd(mcap: Path, rrd: Path, run_id: str) -> tuple[bool, dict]:
    """(written, the converter's figures) of ``rrd`` from ``mcap``: a problem here must not lose
    the run's MCAP, so it is a note on stderr, not an error."""
    try:
        from ambhil.bridge.recording.replay import to_rerun
        from ambhil.bridge.cli.progress import Progress    # rich: slow to import, only when drawing
        with Progress(f"writing {rrd.name}") as bar:
            return True, to_rerun(str(mcap), str(rrd), recording_id=run_id, progress=bar)
    except Exception as e:
        print(f"ambhil run: could not write {rrd}: {e}", file=sys.stderr)
        return False, {}


def orbit_report(mcap: str, clearances: list[float], stations: list[str]) -> list[tuple[str, float, float]]:
    """(station, largest orbit radius (m), radius / touchdown clearance) from the recorded sensor stream."""
    from ambhil.bridge.recording.load import load_run
    v = load_run(mcap, raw=False)["sensors"]["v"]
    out = []
    for k, (name, c) in enumerate(zip(stations, clearances)):
        if v.shape[1] >= 2 * k + 2:
            r = float(np.max(np.hypot(v[:, 2 * k], v[:, 2 * k + 1]))) if len(v) else 0.0
            out.append((name, r, r / c))
    return out


def read_back(mcap: Path, scene, conv: dict, rrd_ok: bool) -> tuple[list, list, str | None]:
    """(orbits, injected fault events, error) of the summary from the recording: the orbits as
    the .rrd converter measured them (read once, while converting) or read again."""
    orbits, injected, err = [], [], None
    if not mcap.exists():
        return orbits, injected, err
    try:
        clr, names = [a.clearance for a in scene.plant.ambs], [a.name for a in scene.plant.ambs]
        if rrd_ok and len(conv.get("orbit_max_m", ())) == len(names):
            orbits = [(nm, r, r / c) for nm, r, c in zip(names, conv["orbit_max_m"], clr)]
        else:
            orbits = orbit_report(str(mcap), clr, names)
    except Exception as e:
        err = str(e)
    if scene.faults:
        try:
            from ambhil.bridge.recording.load import load_run
            injected = [dict(json.loads(e.text), step=e.step, t_s=e.sim_time_ns * 1e-9)
                        for e in load_run(str(mcap))["events"] if e.kind_name == "FAULT_INJECTED"]
        except Exception as e:
            err = err or str(e)
    return orbits, injected, err


def recorded_samples(mcap: Path) -> int | None:
    """Sensor samples in a recording whose recorder gave no summary (None if unreadable)."""
    if not mcap.exists():
        return None
    try:
        from ambhil.bridge.recording.load import load_run
        return len(load_run(str(mcap))["sensors"]["v"])
    except Exception:
        return None


def mark_failed(*paths: Path, why: str | None = None) -> list[Path]:
    """Rename a failed run's files ``<run-id>.mcap`` -> ``<run-id>.failed.mcap`` (same for the
    .rrd): a failed run is recognisable from its file names; the MCAP's ``ambhil.run_end``
    metadata says why: ``why`` goes into it where the recorder saw the run end normally
    (bridge/recording/recover.py, mark_run_failed).  Returns the new paths of the files that existed."""
    out = []
    for p in paths:
        if p.exists():
            if why and p.suffix == ".mcap":
                from ambhil.bridge.recording.run_end import mark_run_failed
                try:
                    mark_run_failed(str(p), why)
                except Exception as e:      # the file stays as the recorder wrote it
                    print(f"ambhil run: note: could not write the verdict into {p}'s run_end: {e}",
                          file=sys.stderr)
            q = p.with_name(f"{p.stem}.failed{p.suffix}")
            p.replace(q)
            out.append(q)
    return out
