#!/usr/bin/env python3
"""Independent check of a scan3d session recording with the official MCAP reader (PyPI `mcap`,
tested with 1.6.0).

    mcap_check.py SESSION_DIR (--expect counts.json | --expect-json '{"topic": count, ...}')
                  [--allow-extra-topics] [--server-made TOPIC]... [--complete]

Reads every `*.mcap` file in SESSION_DIR (in name order; a single .mcap file may be given
instead) record by record and checks that:
- the per-topic message counts equal the expected ones (a JSON object mapping topic -> count);
  topics recorded but not expected are a mismatch unless --allow-extra-topics; a --server-made
  topic (written by the server itself, e.g. clock models) must only be non-empty;
- every message's data starts with the magic of its channel's encoding: `S3DP` (53 33 44 50)
  for wire frames (`scan3d-frame`), `S3DR` (53 33 44 52) for server-made records
  (`scan3d-record`: clock models; their MCAP sequence is 0, "not set" in the MCAP spec);
- no (topic, sequence) pair of a wire frame occurs twice, across all files of the session;
- chunk CRCs match.

A file cut short by a crash is tolerated (the server continues a session in a new file after a
restart): its complete records count, the torn tail is reported. A torn tail is a file that ends
before its footer, or whose last chunk fails its CRC with only zero bytes after it (what a crash
can leave on ext4). With --complete, every file must end with its footer (a clean shutdown).

Prints a summary; exit status 0 if everything matches, 1 on a mismatch or damaged file, 2 on
bad usage or an unreadable session.
"""

import argparse
import json
import os
import sys
from collections import Counter
from dataclasses import dataclass, field

try:
    from mcap.exceptions import EndOfFile
    from mcap.records import Channel, Footer, Message
    from mcap.stream_reader import StreamReader
except ImportError:
    print("mcap_check: the Python `mcap` package is missing (pip install mcap)", file=sys.stderr)
    sys.exit(2)

S3DP_MAGIC = b"S3DP"  # 53 33 44 50
# Message encoding of a channel -> the magic its messages start with.
MAGIC_BY_ENCODING = {"scan3d-frame": S3DP_MAGIC, "scan3d-record": b"S3DR"}
MAX_DUPLICATES_SHOWN = 10


class Truncated(Exception):
    """The file ended in the middle of a record."""


class StrictStream:
    """File wrapper for StreamReader that raises Truncated on a short read: the reader itself
    would hand a record its partial bytes (or raise a bare struct.error)."""

    def __init__(self, file):
        self._file = file
        self.position = 0

    def read(self, length=-1):
        data = self._file.read(length)
        self.position += len(data)
        if length is not None and length >= 0 and len(data) < length:
            where = "before its footer" if not data else "inside a record"
            raise Truncated(f"file ends at byte {self.position}, {where}")
        return data

    def rest_is_zero(self):
        """Whether everything after the current position is zero bytes (or nothing)."""
        while True:
            block = self._file.read(1 << 16)
            if not block:
                return True
            if block.count(0) != len(block):
                return False


@dataclass
class FileReport:
    path: str
    size: int
    messages: int = 0
    complete: bool = False
    torn: str = ""  # why the file ends early, if it does
    error: str = ""  # damage that is not a torn tail


@dataclass
class SessionReport:
    files: list = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)
    encodings: dict = field(default_factory=dict)  # topic -> set of message encodings
    bad_magic: Counter = field(default_factory=Counter)  # topic -> messages without their magic
    duplicates: list = field(default_factory=list)  # (topic, sequence, file)
    seen: set = field(default_factory=set)


def read_file(path, session):
    report = FileReport(path=path, size=os.path.getsize(path))
    channels = {}  # channel id -> (topic, message encoding), per file
    with open(path, "rb") as raw:
        stream = StrictStream(raw)
        reader = StreamReader(stream, validate_crcs=True)
        try:
            for record in reader.records:
                if isinstance(record, Channel):
                    channels[record.id] = (record.topic, record.message_encoding)
                    session.encodings.setdefault(record.topic, set()).add(
                        record.message_encoding
                    )
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        report.error = f"message on unknown channel {record.channel_id}"
                        break
                    account(session, report, channel, record)
                elif isinstance(record, Footer):
                    report.complete = True
        except (Truncated, EndOfFile) as e:
            # Also after the footer: the closing magic is part of a complete file.
            report.complete = False
            report.torn = str(e) or "file ends before its footer"
        except Exception as e:  # noqa: BLE001 - a damaged chunk fails in the decompressor's way
            # (CRCValidationError, zstandard.ZstdError, lz4's RuntimeError, ...). Damage at the
            # very end, followed by nothing but zeros, is a torn tail; anywhere else it is not.
            what = f"{type(e).__name__}: {e}"
            if stream.rest_is_zero():
                report.torn = f"last record is damaged, only zeros after it ({what})"
            else:
                report.error = what
    return report


def account(session, report, channel, message):
    topic, encoding = channel
    report.messages += 1
    session.counts[topic] += 1
    magic = MAGIC_BY_ENCODING.get(encoding)
    if magic is None or not message.data.startswith(magic):
        session.bad_magic[topic] += 1
    if encoding != "scan3d-frame":
        return  # server-made records carry no edge sequence number
    key = (topic, message.sequence)
    if key in session.seen:
        session.duplicates.append((topic, message.sequence, os.path.basename(report.path)))
    else:
        session.seen.add(key)


def session_files(path):
    if os.path.isfile(path):
        return [path]
    if not os.path.isdir(path):
        raise FileNotFoundError(f"{path}: no such file or directory")
    names = sorted(n for n in os.listdir(path) if n.endswith(".mcap"))
    return [os.path.join(path, n) for n in names]


def load_expectation(args):
    try:
        if args.expect is not None:
            with open(args.expect, encoding="utf-8") as f:
                expected = json.load(f)
        else:
            expected = json.loads(args.expect_json)
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot read the expectation: {e}") from e
    if not isinstance(expected, dict) or not all(
        isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) and v >= 0
        for k, v in expected.items()
    ):
        raise ValueError("the expectation must be a JSON object mapping topic -> count (int >= 0)")
    return expected


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("session", help="session directory (or one .mcap file)")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--expect", metavar="PATH", help="JSON file: topic -> message count")
    group.add_argument("--expect-json", metavar="JSON", help="inline JSON: topic -> count")
    parser.add_argument(
        "--allow-extra-topics",
        action="store_true",
        help="do not fail on recorded topics missing from the expectation",
    )
    parser.add_argument(
        "--server-made",
        metavar="TOPIC",
        action="append",
        default=[],
        help="a topic the server writes itself (clock models, commands): must hold at least one "
        "message, its count is not compared (repeatable)",
    )
    parser.add_argument(
        "--complete", action="store_true", help="every file must end with its footer"
    )
    args = parser.parse_args(argv)

    try:
        expected = load_expectation(args)
        files = session_files(args.session)
    except (ValueError, OSError) as e:
        print(f"mcap_check: {e}", file=sys.stderr)
        return 2
    if not files:
        print(f"mcap_check: no .mcap files in {args.session}", file=sys.stderr)
        return 2

    session = SessionReport()
    for path in files:
        try:
            session.files.append(read_file(path, session))
        except OSError as e:
            print(f"mcap_check: {path}: {e}", file=sys.stderr)
            return 2

    problems = []
    print(f"session {args.session}: {len(files)} file(s)")
    for f in session.files:
        state = "complete" if f.complete else f"TORN ({f.torn})" if f.torn else "no footer"
        if f.error:
            state = f"DAMAGED ({f.error})"
            problems.append(f"{os.path.basename(f.path)}: {f.error}")
        elif args.complete and not f.complete:
            problems.append(f"{os.path.basename(f.path)}: not complete ({f.torn or 'no footer'})")
        print(f"  {os.path.basename(f.path)}: {f.size} bytes, {f.messages} messages, {state}")

    print("topics (recorded / expected):")
    for topic in sorted(set(session.counts) | set(expected) | set(args.server_made)):
        got = session.counts.get(topic, 0)
        want = expected.get(topic)
        encodings = ",".join(sorted(session.encodings.get(topic, ()))) or "-"
        if want is None and topic in args.server_made:
            verdict = "server-made" if got > 0 else "MISSING"
            if got == 0:
                problems.append(f"{topic}: no server-made messages")
        elif want is None:
            verdict = "extra" if args.allow_extra_topics else "UNEXPECTED"
            if not args.allow_extra_topics:
                problems.append(f"{topic}: {got} messages on a topic not expected")
        elif got == want:
            verdict = "ok"
        else:
            verdict = "MISMATCH"
            problems.append(f"{topic}: {got} messages, expected {want}")
        shown_want = "-" if want is None else want
        print(f"  {topic}: {got} / {shown_want}  [{encodings}]  {verdict}")

    for topic, n in sorted(session.bad_magic.items()):
        encodings = ",".join(sorted(session.encodings.get(topic, ()))) or "?"
        problems.append(f"{topic}: {n} messages do not start with the magic of [{encodings}]")
    if session.duplicates:
        problems.append(f"{len(session.duplicates)} repeated (topic, sequence) pairs")
        for topic, seq, name in session.duplicates[:MAX_DUPLICATES_SHOWN]:
            print(f"  duplicate: {topic} sequence {seq} (again in {name})")

    total = sum(session.counts.values())
    if problems:
        print(f"FAIL: {total} messages; " + "; ".join(problems))
        return 1
    print(f"OK: {total} messages, each with its encoding's magic, no repeated (topic, sequence)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
