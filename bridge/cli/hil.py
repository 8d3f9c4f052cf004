"""The argument definitions of the HIL commands: `plant`, `controller`, `record` (the zenoh
processes, bridge/cli/processes.py), `run` (the three of them on this host, bridge/cli/run.py),
`replay`, `recover` (bridge/cli/recordings.py), `certs` and `key` (bridge/cli/keyfile.py).  Every value is typed here, once, by
its argparse ``type`` (bridge/cli/arguments.py); the handlers get parsed values."""
from __future__ import annotations

from ambhil.bridge.cli.arguments import (MODES, RUNGS, INTEGRATORS, add_fault_flag, add_law_flag, cpu_list,
                                         cpu_wake_us, delay, overrun_limit, positive_ms, seconds)
from ambhil.bridge.cli.convention import add_json, add_out, arg_type, command
from ambhil.bridge.cli.keyfile import add_key_flags, cmd_key
from ambhil.bridge.cli.processes import cmd_certs, cmd_controller, cmd_plant, cmd_record, record_file
from ambhil.bridge.cli.recordings import cmd_recover, cmd_replay
from ambhil.bridge.cli.run import run
from ambhil.bridge.cli.run_setup import PLACEMENTS
from ambhil.bridge.cli.run_transport import TRANSPORTS

LISTEN_HELP = ("endpoint to listen on, for peers that join later (default: a free port on each local "
               "address that reaches a tcp --connect endpoint: loopback on one host, the "
               "network interface towards the plant across hosts)")
ROLE_NEEDS_ID = ("plant", "controller", "record")


def _common(p, scene: bool = True) -> None:
    """The flags of every process command and of `run`."""
    role = p.prog.split()[-1]
    if scene:
        p.add_argument("scene", metavar="SCENE", help="scene TOML file")
    p.add_argument("--run-id", required=role in ROLE_NEEDS_ID,
                   help="run identifier (key expressions ambhil/<run-id>/...)"
                        + ("" if role in ROLE_NEEDS_ID else "; default: <scene>-<date>-<time>"))
    add_json(p)
    p.add_argument("--start-timeout", type=arg_type(seconds, "s"), default=30.0, metavar="S",
                   help="s a peer may be absent (no liveliness token) before giving up; a peer "
                        "that is there, even still starting, is waited for as long as it lives")
    p.add_argument("--secure", metavar="DIR",
                   help="mutual TLS with the certificates in DIR (`ambhil certs DIR`) and zenoh access "
                        "control allowing each role only its own keys of the run; endpoints must be "
                        "tls/HOST:PORT (docs/hil.md, Secure runs)")
    add_key_flags(p, run=role == "run")
    if role in ROLE_NEEDS_ID:
        p.add_argument("--cpus", type=arg_type(cpu_list, "cpus"), help="pin this process (all its threads) to "
                       "these CPUs, e.g. 1 or 0,1 (set before zenoh starts its threads)")


def _plant_flags(p) -> None:
    """The plant's flags, of `plant` and of `run`."""
    p.add_argument("--mode", choices=MODES, default="lockstep",
                   help="lockstep: each step waits for the controller's reply; realtime: paced by the wall clock")
    p.add_argument("--duration", type=arg_type(seconds, "s"), metavar="S",
                   help="simulated s (default: [simulation] duration or 1 s)")
    p.add_argument("--delay", type=arg_type(delay, "latency"), default="0", metavar="LATENCY",
                   help="loop latency: the currents reach the coils this late: periods (2, 1.5), 1.5T, 150us or "
                        "0.2ms; a fraction of a period must be a whole number of plant steps (see --h)")
    p.add_argument("--h", type=arg_type(seconds, "s"), metavar="S",
                   help="plant step, s; the controller period must be a multiple (default: [simulation] step)")
    p.add_argument("--cpu-wake-us", type=arg_type(cpu_wake_us, "us"), default=0, metavar="US",
                   help="realtime: while the run lasts, ask the kernel (PM QoS, /dev/cpu_dma_latency) to keep "
                        "the CPUs' wake-up latency <= US (0: idle CPUs poll, no sleep states); 'off' for no "
                        "request; needs write access to the device (root), the summary says if granted")
    p.add_argument("--rt-receive", choices=("auto", "deadline", "callback"), default="auto",
                   help="realtime: how the plant waits for a reply: deadline = blocking receive woken "
                        "at the window's end by a timer thread on another CPU (bridge/process/deadline.py), "
                        "callback = zenoh callback and queue; auto = deadline where possible (the "
                        "summary says which)")
    p.add_argument("--currents-at", choices=("sample", "arrival"), default="sample",
                   help="realtime: when the simulated coils take the controller's reply: sample = over "
                        "the whole period from the sample (the loop sees no latency but --delay); arrival "
                        "= when it arrived (wake lateness + round trip, rounded up to the plant step --h): "
                        "the machine's and network's latency, as a real plant sees it")
    p.add_argument("--rung", choices=RUNGS, help="model rung (default: [model] rung)")
    p.add_argument("--integrator", choices=INTEGRATORS, help="plant integrator (default: [simulation] integrator)")
    add_fault_flag(p)


def _add_plant(sub) -> None:
    p = command(sub, "plant", "the plant process: integrates the rotor, publishes sensor displacements")
    _common(p)
    p.add_argument("--listen", required=True, help="zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT",
                   help="endpoints to connect to (e.g. the recorder)")
    _plant_flags(p)
    p.add_argument("--reply-timeout", type=arg_type(positive_ms, "ms"), metavar="MS",
                   help="real time: declare the controller dead after MS without any reply (default "
                        "10 controller periods); lockstep: last-resort cap on waiting for a live "
                        "controller (default 300000 = 5 min; a dead one is caught by liveliness)")
    p.add_argument("--max-overruns", type=int, metavar="N", help="realtime: halt after N overruns (default: never)")
    p.add_argument("--wait-recorder", action="store_true", help="start only once a recorder is present")
    p.add_argument("--law", metavar="SPEC", help="the law the controller runs, as given to it (named in the "
                   "RunMeta; the plant never loads it) (default: the scene's)")
    p.set_defaults(func=cmd_plant)


def _add_controller(sub) -> None:
    p = command(sub, "controller", "the controller process: the scene's law (or --law) between the sensor "
                                   "and amplifier models; returns coil currents")
    _common(p)
    p.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT",
                   help="endpoints to connect to (the plant, the recorder)")
    p.add_argument("--listen", metavar="ENDPOINT", help=LISTEN_HELP)
    p.add_argument("--gain-scale", type=float, default=1.0, metavar="K",
                   help="scale the controller output (a deliberately changed controller, for testing)")
    p.add_argument("--rung", choices=RUNGS,
                   help="the plant's model rung (default: [model] rung); under [model] gravity the ancf "
                        "rung's operating currents carry the weight")
    add_law_flag(p)
    p.set_defaults(func=cmd_controller)


def _add_record(sub) -> None:
    p = command(sub, "record", "record all traffic of a run to <out>/<run-id>.mcap")
    _common(p, scene=False)
    add_out(p, "recordings", "the recording <run-id>.mcap")
    p.add_argument("--listen", metavar="ENDPOINT", help=LISTEN_HELP)
    p.add_argument("--connect", nargs="*", default=[], metavar="ENDPOINT", help="endpoints to connect to")
    p.add_argument("--owner-pid", type=int, metavar="PID",
                   help="the `ambhil run` that started this recorder: if it dies, the recording is finished "
                        "(status stopped), renamed <run-id>.failed.mcap and its .failed.rrd written")
    p.add_argument("--source", choices=("plant", "wire"), default="plant",
                   help="plant: sensor samples and currents from the plant's RecordBatch messages, off "
                        "the loop's path (ambhil plant); wire: subscribe to them directly (a plant "
                        "of your own that sends no RecordBatch; the loop then pays for the recorder)")
    p.set_defaults(func=cmd_record, _finalize=record_file)


def _add_run(sub) -> None:
    p = command(sub, "run", "plant + controller + recorder as separate processes; summary; .mcap and .rrd")
    _common(p)
    _plant_flags(p)
    p.add_argument("--reply-timeout", type=arg_type(positive_ms, "ms"), metavar="MS",
                   help="plant: controller dead after MS without any reply (real time, default 10 "
                        "periods); lockstep: last-resort cap (default 5 min)")
    p.add_argument("--max-overruns", type=arg_type(overrun_limit, "limit"), default="1%", metavar="LIMIT",
                   help="realtime: P%% = the run FAILED (exit 1, .failed files) when more than P %% of the periods "
                        "after the warm-up overran (its results are then not the scene's: the summary compares "
                        "its orbits with the in-process loop's); N = the plant halts after N overruns; off = "
                        "neither.  Before the run a calibration says whether this machine can hold the rate")
    p.add_argument("--placement", choices=PLACEMENTS, default="auto",
                   help="CPU placement: auto = plant and controller share the last CPU, the recorder "
                        "gets the others (needs >= 2 CPUs, else none); none = leave it to the OS")
    p.add_argument("--transport", choices=TRANSPORTS, default="auto",
                   help="the link between the run's processes: auto = Unix-domain sockets where they "
                        "work, else TCP loopback (the summary says which); unix; tcp")
    p.add_argument("--no-record", action="store_true",
                   help="no recorder process, no .mcap/.rrd (the summary's orbit lines need the recording)")
    p.add_argument("--record-source", choices=("plant", "wire"), default="plant",
                   help="plant: the recorder gets the loop's messages in the plant's batches, off the "
                        "loop's path; wire: it subscribes to them directly (the loop pays; for comparison)")
    add_out(p, "recordings", "<run-id>.mcap and <run-id>.rrd")
    p.add_argument("--strict", action="store_true",
                   help="refuse to run when the sampled loop at the scene's rate and latency is unstable, "
                        "and fail a run in which the plant or controller rejected messages (another "
                        "process published into the run, or malformed traffic)")
    p.add_argument("--endpoint", metavar="ENDPOINT",
                   help="the plant's listen endpoint (default: a free port on 127.0.0.1)")
    p.add_argument("--controller", metavar="CMD",
                   help="run this command as the controller instead of `ambhil controller` (placeholders {scene}, "
                        "{run_id}, {connect} = the plant's and recorder's endpoints, {key_file} = the run's key "
                        "file, also in $AMBHIL_KEY_FILE), e.g. "
                        "\"ambhil controller {scene} --run-id {run_id} --connect {connect}\" (it reads "
                        "$AMBHIL_KEY_FILE); its exit code says how it ended")
    add_law_flag(p, "the controller process")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="show each process's start-up steps (model, kernels, waiting, pairing); "
                        "without it only a kernel compilation and the plant's start are shown")
    p.set_defaults(func=run)


def _add_replay(sub) -> None:
    p = command(sub, "replay", "MCAP -> rerun .rrd, or replay the sensor stream into a controller")
    p.add_argument("mcap", metavar="RUN.mcap", help="a recording (ambhil run / ambhil record)")
    add_out(p, None, "the .rrd, named like the recording (default: the recording's folder)")
    p.add_argument("--to-controller", action="store_true",
                   help="re-publish the sensors to a controller and compare its currents with the recorded ones")
    p.add_argument("--scene", metavar="SCENE",
                   help="with --to-controller: start `ambhil controller SCENE` as the controller under test")
    p.add_argument("--gain-scale", type=float, default=1.0, metavar="K", help="with --scene: scale that controller's output")
    add_law_flag(p, "the controller under test (with --scene)")
    p.add_argument("--listen", metavar="ENDPOINT", help="endpoint the replay listens on (default: a free loopback port)")
    p.add_argument("--run-id", help="run id for the replay traffic (default: replay-<pid>)")
    p.add_argument("--controller-cmd", metavar="CMD",
                   help="with --to-controller: launch CMD as the controller under test, any language "
                        "({run_id} and {connect} in CMD are replaced; also in $AMBHIL_RUN_ID, "
                        "$AMBHIL_CONNECT); docs/controllers.md")
    p.add_argument("--tolerance", type=float, default=0.0, metavar="A",
                   help="largest allowed current deviation per axis, A (0 = bit for bit)")
    p.add_argument("--start-timeout", type=arg_type(seconds, "s"), default=30.0, metavar="S",
                   help="s a controller started by hand may be absent before giving up")
    p.add_argument("--secure", metavar="DIR",
                   help="with --to-controller: mutual TLS and access control with the certificates in DIR "
                        "(the replay poses as the plant: its certificate; --listen must be tls/HOST:PORT, "
                        "default a free tls/127.0.0.1 port)")
    add_key_flags(p)
    add_json(p)
    p.set_defaults(func=cmd_replay)


def _add_certs_and_recover(sub) -> None:
    p = command(sub, "certs", "make a CA and a certificate per role (plant, controller, recorder) for --secure")
    p.add_argument("dir", metavar="DIR", help="folder for ca.pem and <role>.pem/.key (created)")
    p.add_argument("--host", default="127.0.0.1", help="address or name the certificates are valid for")
    p.add_argument("--days", type=int, default=825, help="validity, days")
    p.add_argument("--force", action="store_true", help="replace existing certificates")
    add_json(p)
    p.set_defaults(func=cmd_certs)

    p = command(sub, "key", "write a new run secret to a key file (mode 0600) for --key-file")
    p.add_argument("file", metavar="FILE", help="the key file to write (64 hex digits, mode 0600)")
    p.add_argument("--force", action="store_true", help="replace FILE if it exists")
    add_json(p)
    p.set_defaults(func=cmd_key)

    p = command(sub, "recover", "restore the readable part of a truncated MCAP (e.g. a recorder killed with SIGKILL)")
    p.add_argument("src", metavar="SRC", help="the truncated recording (never modified)")
    p.add_argument("dst", nargs="?", metavar="DST", help="the new file (default: SRC with .recovered.mcap)")
    p.add_argument("--force", action="store_true", help="replace DST if it exists")
    add_json(p)
    p.set_defaults(func=cmd_recover)


def add_parsers(sub) -> None:
    """Register the HIL commands, in the order `ambhil --help` lists them."""
    for add in (_add_plant, _add_controller, _add_record, _add_run, _add_replay, _add_certs_and_recover):
        add(sub)
