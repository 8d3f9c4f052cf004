import os
import sys

import pytest
from pathlib import Path

# The source imports only as the installed `ambhil.*` (the editable install maps the layout's folders
# there), so the repository root stays OFF sys.path: with it, a leftover import of an old top-level
# name (`plant.model`, `bridge.cli`) would still resolve here and fail only for a user.  `python -m
# pytest` puts the working directory first; it is taken out again.  The tests/ folder itself is on
# sys.path (pytest puts it there), so a test imports a sibling helper as `helpers`, `test_nodes`.
ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if os.path.realpath(p or os.curdir) != str(ROOT)]


@pytest.fixture(scope="session")
def hard_recording(tmp_path_factory):
    """A built-in run of scenes/paper_3amb_misaligned.toml that saturates (current limit just above
    the operating point) through a 2-sample controller delay: the recording the conformance tests of
    test_controllers.py and test_python_controller.py replay.  Here, session-scoped, it is run once
    for both files (a module fixture imported into the second file ran it twice)."""
    import subprocess
    d = tmp_path_factory.mktemp("hard")
    text = (ROOT / "scenes" / "paper_3amb_misaligned.toml").read_text().replace("current_limit = 4.0",
                                                                               "current_limit = 1.4")
    assert "current_limit = 1.4" in text
    text = text.replace("[controller]", "[controller]\ndelay_samples = 2", 1)
    scene = d / "hard.toml"
    scene.write_text(text)
    r = subprocess.run([sys.executable, "-m", "ambhil.bridge.cli", "run", str(scene), "--duration", "0.05",
                        "--rung", "modal", "--run-id", "hard", "--out", str(d)],
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    mcap = next(p for p in (d / "hard.mcap", d / "hard.failed.mcap") if p.exists())
    return mcap, r


# The slow tests: each over ~10 s (its call, or the setup of a fixture only slow tests use) on a busy
# 2-core machine, nearly all of them OS processes over zenoh (`ambhil run`, a fault campaign, the
# example controllers; the Rust one builds its crate with cargo on first use).  They are marked
# `slow` here, in one list, not in each file: `-m "not slow"` leaves them out, the fast subset for
# the edit-test loop (README, "Tests"); the full suite (`./ambhil-dev test`, CI) runs them all.
# A name that its file no longer defines is an error, so the list cannot silently go stale.
SLOW = {
    "test_ancf.py": ("test_lockstep_run_over_zenoh_equals_in_process",
                     "test_lockstep_run_with_gravity_preloads_the_controller_process"),
    "test_auth.py": ("test_run_strict_fails_on_foreign_traffic_and_keeps_the_orbit",),
    "test_attacks.py": ("test_forged_id_currents_are_rejected_auth_and_change_nothing",
                        "test_forged_id_in_real_time_at_2khz_is_rejected_and_the_run_completes",
                        "test_replayed_record_batches_are_rejected_and_stay_out_of_the_recording",
                        "test_plus_one_flood_is_rejected_and_strict_fails",
                        "test_seq_stall_sample_is_rejected_auth_and_does_not_stall",
                        "test_seq_stall_in_an_unauthenticated_run_does_not_stall_the_controller",
                        "test_forged_events_are_not_obeyed_and_recorded_as_foreign",
                        "test_first_joiner_is_a_stranger_and_the_real_controller_pairs",
                        "test_early_announcer_does_not_deny_the_run",
                        "test_recorder_certificate_can_neither_end_nor_stall_a_secure_run"),
    "test_example_zone_b.py": ("test_the_example_is_zone_b_or_better_at_every_operating_speed",),
    "test_law_kinds_run.py": ("test_lockstep_run_of_each_law_kind_equals_simulate_bit_for_bit",
                              "test_realtime_run_with_a_python_law_names_it_and_answers_every_sample"),
    "test_law_cli.py": ("test_replay_to_controller_checks_a_law_against_its_recording",
                        "test_test_controller_runs_its_cases_with_the_law",
                        "test_a_law_that_raises_in_a_run_ends_it_with_one_line_and_the_recording_is_kept",
                        "test_lockstep_run_with_a_law_equals_simulate_bit_for_bit",
                        "test_simulate_with_a_law_that_raises_is_one_fault_line_and_keeps_its_outputs",
                        "test_a_law_that_cannot_be_loaded_is_a_user_error_before_anything_starts"),
    "test_law_client.py": ("test_walkthrough_plant_example_and_recorder_equal_the_builtin_run",
                           "test_ambhil_run_with_the_example_as_controller_equals_the_builtin_run",
                           "test_conformance_passes_the_example_bit_for_bit_through_saturation_and_delay",
                           "test_a_law_that_raises_ends_the_run_with_its_one_line"),
    "test_controllers.py": ("test_rust_controller_run_equals_builtin_run",       # + the cargo build
                            "test_conformance_command_passes_rust_controller_bit_for_bit",
                            "test_rust_controller_refuses_two_plants",
                            "test_conformance_table_names_the_axis_of_a_deviation",   # hard_recording
                            "test_conformance_refuses_a_controller_that_dies"),
    "test_ancf_contact.py": ("test_drop_on_the_ancf_rung_matches_the_full_rung",),
    "test_contact_hil.py": ("test_lockstep_drop_run_equals_simulate_bit_for_bit_with_its_contact_events",
                            "test_realtime_run_publishes_the_contact_events_and_summary"),
    "test_faults.py": ("test_one_touchdown_clearance_in_analyze_simulate_and_campaign",
                       "test_campaign_against_a_controller_command_agrees_with_in_process",
                       "test_campaign_prints_a_pass_fail_table_and_exits_1_on_a_failed_case",
                       "test_lockstep_run_with_faults_equals_simulate_and_records_the_events"),
    "test_hil_cli.py": ("test_predicted_unstable_latency_diverges_over_zenoh_and_its_stable_neighbour_completes",
                        "test_run_fails_like_simulate_on_a_loop_predicted_to_grow",
                        "test_run_leaves_mcap_and_rrd_and_summary",           # these six share `recorded`
                        "test_lockstep_over_zenoh_equals_in_process",
                        "test_replay_to_controller_pass_and_fail",
                        "test_replay_to_rrd_and_recover",
                        "test_run_shows_startup_progress",
                        "test_simulate_writes_the_recording_of_a_run_with_the_same_data",
                        "test_failed_run_files_are_marked",
                        "test_run_over_tcp_without_recorder",
                        "test_fractional_latency_over_zenoh_equals_in_process",
                        "test_sigterm_stops_a_run_started_with_sigint_ignored_as_ctrl_c_does",
                        "test_killed_run_takes_its_processes_with_it",
                        "test_a_full_disk_ends_the_run_with_the_file_named_and_marked",
                        "test_a_peer_killed_during_the_run_is_named_and_the_plant_reports_its_steps"),
    "test_python_controller.py": ("test_python_controller_run_equals_builtin_run",
                                  "test_python_controller_restart_via_ambhil_run",
                                  "test_conformance_command_passes_python_controller_bit_for_bit",
                                  "test_conformance_fails_fast_when_the_controller_dies_before_pairing"),
    "test_scene_fuzz.py": ("test_scene_fuzz",),
    "test_secure.py": ("test_secure_run_equals_the_plain_run_bit_for_bit",),
    "test_timing_study.py": ("test_grid_results_are_identical_in_process_and_on_a_local_cluster",
                             "test_force_noise_on_the_full_rung_gives_a_finite_variance",
                             "test_no_non_finite_figure_anywhere_in_a_study_result"),
}


@pytest.hookimpl(tryfirst=True)           # before -m selects by marker
def pytest_collection_modifyitems(config, items):
    checked = set()
    for item in items:
        names = SLOW.get(item.path.name)
        if not names:
            continue
        if item.path.name not in checked:
            checked.add(item.path.name)
            gone = [n for n in names if not hasattr(item.module, n)]
            if gone:
                raise pytest.UsageError(f"tests/conftest.py SLOW names {', '.join(gone)}, which "
                                        f"tests/{item.path.name} no longer defines")
        if getattr(item, "originalname", item.name) in names:
            item.add_marker(pytest.mark.slow)


# zenoh-python runs each Python callback on a non-daemon thread that ends only when zenoh drops
# the callback; one that zenoh keeps (e.g. a liveliness subscriber's history query still
# pending when its session closed) makes the interpreter wait for it at exit forever, after the
# summary was printed.  The product's zenoh processes exit hard for the same reason
# (bridge/cli/main.py HARD_EXIT); the test run does too, with pytest's exit status, but only then.
_EXIT_STATUS = [None]


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS[0] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    import os
    import threading
    stuck = [t.name for t in threading.enumerate()
             if t is not threading.main_thread() and not t.daemon and t.is_alive()]
    if stuck and _EXIT_STATUS[0] is not None:
        sys.stdout.flush()
        sys.stderr.write(f"conftest: {len(stuck)} zenoh callback thread(s) still alive at exit "
                         f"({', '.join(stuck[:3])}); exiting without waiting for them\n")
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[0])
