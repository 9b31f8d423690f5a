"""Where a migration's time goes (diagnostic): ``python -m bench --only migtrace``.

Runs the migration benchmark's two daemons through ``python -m bench.migtrace up ...``, which
wraps, before handing over to ``cmion_mesh.cli.main``, the functions a migration passes through and
prints one ``TRACE <label> <start_ns> <duration_ns> <thread>`` line per call
(``time.perf_counter_ns``: ``CLOCK_MONOTONIC``, one clock for every process). The measuring
process notes the window of each migration and adds up, per label, the calls of both daemons
that started inside it. Calls nest (``_on_prepare`` includes ``unpack`` and the record writes),
so the rows are not to be summed; the ``on loop`` / ``on a worker`` labels say where each runs.
Wrappers cost a few microseconds per call.

For digging further, two environment variables of the wrapped daemons: ``BENCH_STACKS=<seconds>``
prints every thread's innermost frames (``STACK`` lines) at that interval, and
``BENCH_SWITCH_INTERVAL=<seconds>`` sets ``sys.setswitchinterval`` (to test GIL hand-over effects).
"""

from __future__ import annotations

import functools
import os
import re
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from bench.migration import COMPANION, DELTA_SCRATCH, OVERHEAD, SIZES, A, B, Migrations, size_name, two_daemons
from bench.registry import Options, Row
from bench.stats import summarize
from cmion_mesh.procs import unique_mesh

TRACE = re.compile(r"^TRACE (.+) (\d+) (\d+) (\S+)$")
_print_lock = threading.Lock()


def log(text: str) -> None:
    print(f"  [migtrace] {text}", flush=True)


def _emit(label: str, start: int, duration: int) -> None:
    thread = f"{threading.current_thread().name.replace(' ', '_')}@{threading.get_native_id()}"
    line = f"TRACE {label} {start} {duration} {thread}\n"
    with _print_lock:
        sys.stdout.write(line)
        sys.stdout.flush()


def wrap(owner: Any, attr: str, label: str | Callable[..., str], min_ns: int = 0) -> None:
    original = getattr(owner, attr)

    @functools.wraps(original)
    def timed(*args: Any, **kwargs: Any) -> Any:
        start = time.perf_counter_ns()
        try:
            return original(*args, **kwargs)
        finally:
            duration = time.perf_counter_ns() - start
            if duration >= min_ns:
                _emit(label(*args, **kwargs) if callable(label) else label, start, duration)

    setattr(owner, attr, timed)


def request_of(key: str) -> str:
    """``<component>/<request>`` of a request key (``.../rq/<component>/<request>[/<sender>]``), else its last chunk."""
    parts = key.split("/")
    if "rq" in parts[:-2]:
        i = parts.index("rq")
        return f"{parts[i + 1]}/{parts[i + 2]}"
    return parts[-1]


def _timed_session_get(self: Any, selector: str, payload: bytes | None, timeout: float) -> tuple[str, int, Any]:
    """The ``session.get()`` call of a ``ZenohTransport`` query, timed: (what, when it returned, replies)."""
    import zenoh

    what = request_of(selector)
    t0 = time.perf_counter_ns()
    replies = self._session.get(selector, payload=payload, timeout=timeout, target=zenoh.QueryTarget.ALL,
                                consolidation=zenoh.ConsolidationMode.NONE)
    t1 = time.perf_counter_ns()
    _emit(f"zenoh:session.get() call:{what}", t0, t1 - t0)
    return what, t1, replies


def _reply(selector: str, reply: Any) -> Any:
    from cmion_mesh.transport.base import Reply

    ok = reply.ok
    if ok is not None:
        return Reply(str(ok.key_expr), ok.payload.to_bytes(), True)
    err = reply.err
    return Reply(selector, err.payload.to_bytes() if err is not None else b"", False)


def _traced_get(self: Any, selector: str, payload: bytes | None = None, *, timeout: float = 10.0) -> Any:
    """``ZenohTransport.get`` with the ``session.get()`` call and the wait for replies timed apart."""
    what, t1, replies = _timed_session_get(self, selector, payload, timeout)
    out: list[Any] = []
    for reply in replies:
        if not out:
            _emit(f"zenoh:get -> first reply:{what}", t1, time.perf_counter_ns() - t1)
        out.append(_reply(selector, reply))
    _emit(f"zenoh:get -> final:{what}", t1, time.perf_counter_ns() - t1)
    return out


def _traced_get_first_later(self: Any, selector: str, payload: bytes | None = None, *, timeout: float = 10.0) -> Any:
    """``ZenohTransport.get_first_later`` with the ``session.get()`` call and the wait for the reply timed apart."""
    what, t1, replies = _timed_session_get(self, selector, payload, timeout)

    def first() -> Any:
        for reply in replies:
            _emit(f"zenoh:get -> first reply:{what}", t1, time.perf_counter_ns() - t1)
            return _reply(selector, reply)
        return None

    return first


def install() -> None:
    from cmion_mesh import ion
    from cmion_mesh.migration import custody, handshake, identity, signing
    from cmion_mesh.migration import manager as migration
    from cmion_mesh.migration import sections as sections_module
    from cmion_mesh.migration.incoming import Incoming
    from cmion_mesh.migration.journal import Journal
    from cmion_mesh.migration.ledger import Records
    from cmion_mesh.migration.manager import MigrationManager
    from cmion_mesh.migration.outgoing import Outgoing
    from cmion_mesh.migration.sections import IncomingSection, SectionStore
    from cmion_mesh.migration.uploads import Uploads
    from cmion_mesh.transport import zenoh as zenoh_transport

    def append_label(_self: Any, _payload: bytes, state: str = "", **_k: Any) -> str:
        return f"ledger append+fdatasync:{state or 'entry'}"

    def request_label(_transport: Any, key: str, *_a: Any, **_k: Any) -> str:
        return f"send_request:{request_of(key)}"

    wrap(Journal, "append", append_label)
    wrap(Journal, "rewrite", "ledger compaction")
    wrap(Records, "put", lambda _self, record, *_a, **_k: f"Records.put:{record.state}")
    wrap(sections_module, "write_files", lambda files, last=None: f"write+fsync:batch of {len(files)}{' + record' if last else ''}")
    wrap(zenoh_transport.ZenohTransport, "declare_token", "zenoh:declare_token")
    wrap(SectionStore, "write", "write+fsync:sections")
    wrap(IncomingSection, "add", "section chunk: copy+hash (write beside)")
    wrap(IncomingSection, "_write_out", "section chunk: pwrite+fadvise (beside)")
    wrap(IncomingSection, "finish", "section received: fsync+rename")
    wrap(SectionStore, "read_many", "read+check sections held")
    wrap(handshake, "read_manifest", "read_manifest(parse+XSD)")
    wrap(identity, "decode_section", "decode_section(msgpack)")
    wrap(identity.Identity, "pack_sections", "pack_sections(msgpack+sha256+XML)")
    wrap(signing, "sign", "sign(ed25519)")
    wrap(custody, "verify_chain", "verify custody chain")
    wrap(migration, "send_request", request_label)
    wrap(zenoh_transport.ZenohTransport, "alive", "liveliness_get(target alive?)")
    zenoh_transport.ZenohTransport.get_first_later = _traced_get_first_later  # type: ignore[method-assign]
    zenoh_transport.ZenohTransport.get = _traced_get  # type: ignore[method-assign]
    wrap(ion.Simulation, "_on_query",
         lambda _sim, component, query: f"on a worker:query {request_of(query.key)}")
    wrap(ion, "decode", lambda data, kind, **_: f"decode:{getattr(kind, '__name__', 'msg')}", min_ns=100_000)
    wrap(ion, "encode", lambda msg: f"encode:{type(msg).__name__}", min_ns=100_000)
    parts: tuple[tuple[type, str, str], ...] = (
        (Outgoing, "begin", "on loop:begin(source checks)"), (Outgoing, "_maybe_pack", "on loop:_maybe_pack"),
        (MigrationManager, "refresh_sections", "on loop:mind.state()"), (Incoming, "on_prepare", "on loop:on_prepare(target)"),
        (Incoming, "on_commit", "on loop:on_commit(target)"), (MigrationManager, "inhabit", "on loop:inhabit(restore+wake)"),
        (Outgoing, "_send", "on a worker:_send(source)"), (Outgoing, "commit_until_acked", "on a worker:commit_until_acked(source)"),
        (Outgoing, "_ask_have", "on a worker:_ask_have"), (Outgoing, "_send_bulk", "on a worker:_send_bulk(chunks)"),
        (Outgoing, "_prepare", "on a worker:_prepare"),
        (Incoming, "on_have", "on loop:on_have(target)"), (Uploads, "on_sections", "on loop:on_sections(target)"))
    for owner, method, label in parts:
        wrap(owner, method, label)


def run(options: Options, groups: frozenset[str]) -> list[Row]:
    count = 3 if options.quick else 6
    mesh = unique_mesh("bench")
    launcher = (sys.executable, "-m", "bench.migtrace")
    rows: list[Row] = []
    with ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-migtrace-")))
        nodes, client = two_daemons(stack, mesh, tmp, (A, B), companion=COMPANION, launcher=launcher, report=log)
        mig = Migrations(client, nodes)
        stack.callback(mig.close)
        # (name, metric suffix, message setting the mind up, message before each traced migration)
        cases: list[tuple[str, str, dict[str, int], dict[str, int] | None]] = [
            (size_name(size), str(size), {"size": max(0, size - OVERHEAD)}, {"size": max(0, size - OVERHEAD)})
            for size in SIZES]
        big = SIZES[-1]
        cases.append(("10 MiB delta return", "delta", {"size": max(0, big - OVERHEAD - DELTA_SCRATCH), "scratch": DELTA_SCRATCH},
                      None))
        for name, suffix, setup, fresh in cases:
            mig.tell_mind(setup)
            mig.once()
            mig.once()
            windows: list[tuple[int, int, float]] = []
            for _ in range(count):
                if fresh is not None:
                    mig.tell_mind(fresh)  # a fresh blob: the whole document travels
                start = time.perf_counter_ns()
                occurred, _released = mig.once()
                windows.append((start, time.perf_counter_ns(), occurred))
            threading.Event().wait(0.2)  # the last trace lines
            traces = [(m.group(1), int(m.group(2)), int(m.group(3)))
                      for node in nodes.values() if node.daemon is not None
                      for line in list(node.daemon.lines) if (m := TRACE.match(line))]
            per_label: dict[str, list[float]] = defaultdict(list)
            for start, end, _occ in windows:
                sums: dict[str, int] = defaultdict(int)
                for label, t, d in traces:
                    if start <= t <= end:
                        sums[label] += d
                for label, total in sums.items():
                    per_label[label].append(total / 1e9)
            rows.append(Row(f"trace_total_{suffix}", f"{name}: command -> awake at target (whole)", summarize([w[2] for w in windows])))
            for label in sorted(per_label, key=lambda k: -sorted(per_label[k])[len(per_label[k]) // 2]):
                values = per_label[label] + [0.0] * (count - len(per_label[label]))
                rows.append(Row(f"trace_{label}_{suffix}", f"{name}: {label} (sum per migration)", summarize(values)))
            log(f"{name}: {count} traced migrations")
        mig.tell_mind({"scratch": 0})
    return rows


def _stacks(interval: float) -> None:
    import traceback

    me = threading.get_ident()
    names = {}
    while True:
        time.sleep(interval)
        now = time.perf_counter_ns()
        for ident, frame in sys._current_frames().items():
            if ident == me:
                continue
            if ident not in names:
                names = {t.ident: t.name for t in threading.enumerate()}
            stack = traceback.extract_stack(frame)[-3:]
            where = " < ".join(f"{Path(f.filename).name}:{f.name}:{f.lineno}" for f in reversed(stack))
            with _print_lock:
                sys.stdout.write(f"STACK {now} {names.get(ident, ident)} {where}\n")
                sys.stdout.flush()


def main(argv: list[str]) -> int:
    if os.environ.get("BENCH_STACKS"):
        threading.Thread(target=_stacks, args=(float(os.environ["BENCH_STACKS"]),), daemon=True).start()
    if os.environ.get("BENCH_SWITCH_INTERVAL"):
        sys.setswitchinterval(float(os.environ["BENCH_SWITCH_INTERVAL"]))
    install()
    from cmion_mesh.cli.main import main as cli_main

    return cli_main(argv)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    sys.exit(main(sys.argv[1:]))
