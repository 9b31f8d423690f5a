from __future__ import annotations

import sys
import threading
from collections.abc import Generator, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from cmion_mesh.procs import unique_mesh
from cmion_mesh.transport.memory import MemoryNetwork, MemoryTransport

DATA = Path(__file__).parent / "data"
CMION_2011 = DATA / "cmion2011"


@pytest.fixture(scope="session", autouse=True)
def private_state_home(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Daemons keep durable records under $XDG_STATE_HOME: never the user's own, in tests."""
    import os

    old = os.environ.get("XDG_STATE_HOME")
    os.environ["XDG_STATE_HOME"] = str(tmp_path_factory.mktemp("state-home"))
    yield
    if old is None:
        os.environ.pop("XDG_STATE_HOME", None)
    else:
        os.environ["XDG_STATE_HOME"] = old


@pytest.fixture
def mesh() -> str:
    """A mesh name no other test or parallel run uses."""
    return unique_mesh()


@pytest.fixture
def network() -> MemoryNetwork:
    return MemoryNetwork()


@pytest.fixture
def transport(network: MemoryNetwork) -> Iterator[MemoryTransport]:
    with MemoryTransport(network, "local") as t:
        yield t


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    """Every thread a test starts must be stopped by the end of the test."""
    before = {t.ident for t in threading.enumerate()}
    yield
    def leaked() -> list[str]:
        return [t.name for t in threading.enumerate() if t.ident not in before and t.is_alive() and not t.name.startswith("zenoh-")]
    # Threads that are finishing get a bounded moment to exit.
    for t in [t for t in threading.enumerate() if t.ident not in before]:
        t.join(2.0)
    assert not leaked(), f"threads left running: {leaked()}"


def start_daemon(mesh: str, name: str, *extra: str, port: int | None = None) -> tuple[Daemon, str]:
    """``cmion-mesh up`` in its own process, listening on loopback only; returns it and its endpoint."""
    from cmion_mesh.procs import Daemon, cli_argv, free_port

    endpoint = f"tcp/127.0.0.1:{port or free_port()}"
    daemon = Daemon(cli_argv("up", "--name", name, "--mesh", mesh, "--listen", endpoint, "--no-multicast", *extra), name=name)
    try:
        daemon.wait_line("up in mesh", 20)
    except BaseException:
        daemon.kill()
        raise
    return daemon, endpoint


from cmion_mesh.procs import Daemon  # noqa: E402  (for the annotation above)
from tests.helpers.browser import chromium_browser  # noqa: E402, F401  (the real-browser fixture, for the web page tests)

# --- test tiers ------------------------------------------------------------------------------------
#
# Every test has exactly one tier, a marker, so that ``pytest -m unit`` (seconds, a contributor's
# first run), ``-m mesh`` and ``-m system`` each run one kind; plain ``pytest`` runs them all.
#
#   unit    pure code and the in-memory transport, in this process: no child process, no zenoh
#           session. Guaranteed, not hoped for: while a unit test runs (its setup and call) starting
#           a process or opening a zenoh session raises and fails the test, naming what it started.
#   mesh    daemons and other child processes, real zenoh sessions (loopback only).
#   system  what needs the machine's own facilities, or long runs: network namespaces (root), a
#           browser (Chromium), the ROS 2 stand-in, espeak-ng; ruff and mypy over the tree, the
#           fuzzing (hypothesis), the bench's smoke runs and its 10,000-schedule handshake simulation.
#
# A test file's tier is TIERS[its stem]; a test of another tier than its file's is listed in
# TIER_OF_TEST ("stem::function") or carries ``@pytest.mark.mesh`` / ``@pytest.mark.system`` /
# ``@pytest.mark.unit`` itself. A test file missing from TIERS fails collection, naming the line
# to add: a silent default would put a new file in whichever tier the default says, unseen, and
# a warning scrolls past; one line in this table is cheap, and the unit guard keeps it honest.

TIER_NAMES = ("unit", "mesh", "system")

TIERS: dict[str, str] = {
    "test_abilities": "unit",
    "test_bench_smoke": "system",
    "test_bench_targets": "mesh",
    "test_boundaries": "unit",
    "test_bulkio": "unit",
    "test_cli": "mesh",
    "test_cli_habits": "mesh",
    "test_cli_help": "unit",
    "test_cli_truth": "mesh",
    "test_cmion_compat": "unit",
    "test_cmion_configs": "unit",
    "test_companion_view": "unit",
    "test_competencies": "unit",
    "test_cross_process": "mesh",
    "test_custody_attacks": "mesh",
    "test_daemon_exit": "mesh",
    "test_delta_migration": "unit",
    "test_demo": "mesh",
    "test_devices": "unit",
    "test_embodiments": "unit",
    "test_event_burst": "mesh",
    "test_examples": "unit",
    "test_execution": "unit",
    "test_fatima": "mesh",
    "test_fatima_protocol": "unit",
    "test_foxglove": "unit",
    "test_fuzz": "system",  # hundreds of random inputs a test: ~20 s of CPU, as much as the whole unit tier
    "test_handshake": "unit",
    "test_handshake_simulation": "unit",
    "test_hostile_inputs": "unit",
    "test_idle": "mesh",
    "test_inbox": "unit",
    "test_invitations": "unit",
    "test_ion": "unit",
    "test_keys": "unit",
    "test_lan": "system",
    "test_launch": "mesh",
    "test_ledger": "unit",
    "test_ledger_crash": "mesh",
    "test_manager": "unit",
    "test_mcp": "mesh",
    "test_migration": "unit",
    "test_migration_crash": "mesh",
    "test_migration_network": "system",
    "test_migration_workers": "unit",
    "test_persistent": "unit",
    "test_planner": "unit",
    "test_presence": "unit",
    "test_quality": "system",
    "test_record": "unit",
    "test_remote_competency": "mesh",
    "test_remote_mind": "unit",
    "test_requests_answered": "mesh",
    "test_ros2_definitions": "unit",
    "test_ros2_rclpy": "system",
    "test_ros2_robot": "system",
    "test_ros2_standin": "system",
    "test_ros2_wire": "unit",
    "test_router": "system",
    "test_rules": "unit",
    "test_security_mtls": "mesh",
    "test_speech": "unit",
    "test_statedir": "unit",
    "test_storage": "unit",
    "test_tap": "mesh",
    "test_llm_mind": "mesh",
    "test_llm_unit": "unit",
    "test_log_catalogue": "unit",
    "test_log_daemons": "mesh",
    "test_logs": "unit",
    "test_ops_settings": "unit",
    "test_ops_systemd": "unit",
    "test_ops_metrics": "unit",
    "test_class_aliases": "unit",
    "test_custody": "unit",
    "test_target_bounds": "mesh",
    "test_outbox": "unit",
    "test_shared_declarations": "unit",
    "test_slow_subscriber": "mesh",
    "test_tiers": "unit",
    "test_transport": "mesh",
    "test_tutorial": "mesh",
    "test_up_service": "mesh",
    "test_view": "system",
    "test_view_graph": "system",
    "test_view_player": "unit",
    "test_view_server": "unit",
    "test_webbody": "system",
    "test_webbody_protocol": "unit",
    "test_webserver": "unit",
    "test_world": "unit",
    "test_world_cli": "mesh",
    "test_xmlsafe": "unit",
}

#: Tests whose tier is not their file's, by "file stem::test function" (every parametrization).
TIER_OF_TEST: dict[str, str] = {
    "test_ops_metrics::test_the_containerfile_health_check_as_written": "system",
    "test_ops_systemd::test_the_unit_file_passes_systemd_analyze_verify": "system",
    "test_up_service::test_service_unit_prints_a_unit_systemd_accepts": "system",
    # a fresh interpreter, to see what an import loads
    "test_boundaries::test_importing_the_library_does_not_load_argparse": "mesh",
    "test_boundaries::test_a_one_shot_command_loads_no_xml_crypto_or_planner": "mesh",
    "test_boundaries::test_a_body_serving_no_page_loads_no_web_server": "mesh",
    "test_boundaries::test_a_companions_birth_loads_one_openssl_and_no_key_serialization": "mesh",
    "test_boundaries::test_a_daemon_without_certificates_or_companion_loads_no_crypto": "mesh",
    "test_boundaries::test_a_daemon_starts_without_the_modules_of_paths_it_may_never_take": "mesh",
    "test_boundaries::test_importing_the_package_loads_none_of_the_modules_behind_its_face": "mesh",
    "test_boundaries::test_the_command_table_lists_every_verb_without_importing_one": "mesh",
    "test_boundaries::test_a_verb_imports_its_own_module_only": "mesh",
    "test_cli_truth::test_every_argument_has_help_text": "unit",
    # daemons, or the components `up` builds (a zenoh session)
    "test_cmion_compat::test_validate_builds_the_components_as_up_does": "mesh",
    "test_cmion_configs::test_a_rule_needing_an_absent_type_loads_and_its_action_fails_with_the_reason": "mesh",
    "test_cmion_configs::test_a_configuration_started_from_another_folder_finds_its_files_in_the_working_directory": "mesh",
    "test_cmion_configs::test_a_file_found_nowhere_names_both_places": "mesh",
    "test_cmion_compat::test_a_misspelt_java_class_is_named_with_the_one_meant": "mesh",
    "test_cmion_compat::test_up_starts_with_standins_listed": "mesh",
    "test_cmion_compat::test_up_starts_cmion_own_test_configuration": "mesh",
    "test_delta_migration::test_a_return_trip_sends_only_the_manifest_and_the_changed_sections": "mesh",
    "test_delta_migration::test_a_corrupted_or_missing_cached_section_is_fetched_again": "mesh",
    "test_delta_migration::test_a_10_mib_section_migrates": "mesh",
    "test_delta_migration::test_a_section_over_the_targets_limit_is_refused_naming_it": "mesh",
    # the stand-in FAtiMA mind in a child process
    # speech through espeak-ng, a program of the machine's, when it is installed
    "test_embodiments::test_operator_command_appears_in_the_world_model": "system",
    "test_fatima_protocol::test_a_flooding_mind_is_held_back_and_the_body_keeps_working": "mesh",
    "test_fatima_protocol::test_a_mind_that_does_not_read_is_disconnected": "mesh",
    # the bench's handshake simulation at full length: tens of seconds of CPU (its short runs stay unit)
    "test_handshake_simulation::test_ten_thousand_schedules_keep_exactly_one_host": "system",
    "test_hostile_inputs::test_daemon_over_zenoh_refuses_and_keeps_answering": "mesh",
    "test_invitations::test_device_tables_name_connect_and_give_birth": "mesh",
    "test_invitations::test_an_invitation_from_the_empty_embodiment_moves_the_companion": "mesh",
    "test_invitations::test_cmions_java_named_configurations_run_as_they_are": "mesh",
    "test_launch::test_a_bad_file_is_refused_with_every_problem_by_line": "unit",
    "test_launch::test_free_ports_come_from_below_the_range_outgoing_connections_take": "unit",
    "test_migration_network::test_two_inhabited_finds_overlaps": "unit",
    "test_quality::test_no_test_reads_private_state": "unit",
    # the module's daemons and recorder (its `session` fixture)
    "test_record::test_the_recording_opens_with_the_mcap_reader_and_holds_the_story": "mesh",
    "test_record::test_record_info_summarises_the_migrations": "mesh",
    "test_record::test_a_killed_recorder_leaves_a_file_the_reader_opens": "mesh",
    "test_record::test_replay_into_a_fresh_mesh_shows_a_listener_the_same_events": "mesh",
    "test_record::test_replay_filters_and_rejects_a_bad_rate": "mesh",
    "test_record::test_replay_stops_at_once_while_it_waits_to_join": "mesh",
    "test_ros2_standin::test_computed_type_hashes_equal_the_real_ros2_constants": "unit",
    "test_router::test_router_cli_errors_are_one_line": "mesh",
    "test_security_mtls::test_acl_generator": "unit",
    "test_security_mtls::test_generated_config_is_accepted_by_zenoh": "unit",
    "test_security_mtls::test_apply_turns_a_plain_config_secure": "unit",
    "test_security_mtls::test_secure_daemons_find_each_other_by_multicast": "system",
    "test_speech::test_espeak_speaks_a_line_of_plausible_length": "system",
    "test_tap::test_keys_are_relative_to_the_mesh_unless_absolute": "unit",
    "test_webbody::test_up_refuses_a_web_address_in_use_naming_it": "mesh",
    "test_webbody_protocol::test_the_page_senses_and_the_body_pushes": "system",  # espeak-ng, when installed
    "test_webbody::test_up_refuses_a_bad_web_address_as_a_usage_error": "mesh",
}


class _Untiered(pytest.Module):
    """A test file with no tier: its collection fails with the line to add."""

    def collect(self) -> list[Any]:
        stem = self.path.stem
        raise self.CollectError(
            f"{self.path.name} has no test tier: add \"{stem}\": \"unit\" (or \"mesh\", \"system\") to TIERS in "
            f"tests/conftest.py -- unit: no child process and no zenoh session (checked when it runs); "
            f"mesh: daemons, child processes, zenoh sessions; system: namespaces, browser, ROS 2 stand-in, tools")


def pytest_pycollect_makemodule(module_path: Path, parent: pytest.Collector) -> pytest.Module | None:
    if module_path.name.startswith("test_") and module_path.stem not in TIERS:
        return _Untiered.from_parent(parent, path=module_path)
    return None


def tier_of(item: pytest.Item) -> str:
    """The one tier of ``item``: its own mark, else TIER_OF_TEST, else its file's."""
    stem = item.path.stem
    marked = {m.name for m in item.iter_markers() if m.name in TIER_NAMES}
    listed = TIER_OF_TEST.get(f"{stem}::{getattr(item, 'originalname', item.name)}")
    if len(marked) > 1 or (marked and listed is not None and marked != {listed}):
        found = sorted(marked | ({listed} if listed else set()))
        raise pytest.UsageError(f"{item.nodeid} has more than one test tier ({', '.join(found)}): keep one")
    if marked:
        return marked.pop()
    if listed is not None:
        return listed
    tier = TIERS.get(stem)
    if tier is None:  # a file pytest_pycollect_makemodule did not see (not named test_*.py)
        raise pytest.UsageError(f"{item.nodeid}: {item.path.name} has no test tier: add {stem!r} to TIERS in tests/conftest.py")
    return tier


@pytest.hookimpl(tryfirst=True)  # before -m reads the markers
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        tier = tier_of(item)
        if item.get_closest_marker(tier) is None:
            item.add_marker(getattr(pytest.mark, tier))


#: What a unit test tried to start (events of ``sys.audit``, and ``zenoh.open``) while it ran.
started_in_unit_test: list[str] = []
_guarding = False
#: The audit events of starting another program (``subprocess`` and everything below it, ``os.system``...).
_SPAWNS = frozenset({"subprocess.Popen", "os.system", "os.posix_spawn", "os.spawn", "os.exec", "os.fork", "os.forkpty"})


class StartedInUnitTest(Exception):
    """A unit test started a process or opened a zenoh session."""


def _refuse(what: str) -> None:
    started_in_unit_test.append(what)
    raise StartedInUnitTest(f"a unit test may not start {what}")


def _audit(event: str, args: tuple[Any, ...]) -> None:
    if _guarding and event in _SPAWNS:
        _refuse(f"a process ({event}: {args[1] if event == 'subprocess.Popen' else args[0]!r})")


_zenoh_open = zenoh.open


def _open(*args: Any, **kwargs: Any) -> Any:
    if _guarding:
        _refuse("a zenoh session (zenoh.open)")
    return _zenoh_open(*args, **kwargs)


# An audit hook cannot be removed: it checks a flag, set only while a unit test runs (in this
# process; each xdist worker has its own).
sys.addaudithook(_audit)
zenoh.open = _open


def _guarded(item: pytest.Item) -> Generator[None, Any, Any]:
    global _guarding
    if item.get_closest_marker("unit") is None:
        return (yield)
    started_in_unit_test.clear()
    _guarding = True
    try:
        return (yield)
    finally:
        _guarding = False
        if started_in_unit_test:  # failed even if the code under test caught the exception
            pytest.fail(f"{item.nodeid} is a unit test but started {started_in_unit_test[0]}; "
                        "a unit test stays in this process with no zenoh session: give it its tier in "
                        "tests/conftest.py (TIER_OF_TEST) or mark it @pytest.mark.mesh / @pytest.mark.system",
                        pytrace=False)


# Setup and call, not teardown: the teardown of a unit test that ends a module also ends the
# module's fixtures, which may be a mesh test's daemons.
@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item: pytest.Item) -> Generator[None, Any, Any]:
    return (yield from _guarded(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Generator[None, Any, Any]:
    return (yield from _guarded(item))
