"""Per-artifact cost of the store on an S3-compatible object store against the local store.

What the pipeline pays per artifact: a cache-hit check (`has` + `intact`), a publish (with its
computation counter line) and a read of the arrays back. The same artifacts go through a local
store (a temp folder) and through `s3://` on a moto S3 server this script starts on localhost,
over HTTP, with the client a user's bucket gets (obstore, `AWS_ENDPOINT_URL`). moto is a
Python server sharing the machine's cores with the client, so its figure is a pessimistic one
for a real S3-compatible server; the object requests per artifact are counted too.

With `--run-sequences N` (default 2) it then runs `embody run` on N synthetic sequences
(cheap settings: no render, critic or collision, 1 IK iteration) with the store on the S3
server, twice (cold, then warm), and counts the requests each run sends per sequence, the
run's own (manifest, claim lease, shared steps) included.

    python benchmarks/object_store.py [--n 40] [--frames 150] [--rounds 5] [--run-sequences 2]

Prints `RESULT local_ms=... s3_ms=... overhead_ratio=... requests_per_artifact=...
requests_per_sequence=... warm_requests_per_sequence=...` (`overhead_ratio` = S3 ms / local
ms per artifact, best round of each; target ≤ 2).
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
import uuid
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _artifact(rng: np.random.Generator, frames: int) -> dict[str, np.ndarray]:
    """The shape of a retarget artifact: joint trajectory, root, a few per-frame scalars."""
    return {"q": rng.normal(size=(frames, 43)).astype(np.float32),
            "root": rng.normal(size=(frames, 7)).astype(np.float32),
            "err": rng.random(frames).astype(np.float32)}


def _cycle(store, keys: list[str], arrays: list[dict[str, np.ndarray]]) -> float:
    """ms per artifact for miss-check + publish + record + hit-check + read."""
    t0 = time.perf_counter()
    for key, a in zip(keys, arrays):
        assert not store.has("retarget", key)
        assert store.publish("retarget", key, a, {"fps": 30.0}, {"inputs": {}})
        store.record("retarget", key, sequence=key[:8], published=True)
        assert store.has("retarget", key) and store.intact("retarget", key)
        store.read("retarget", key)
    return (time.perf_counter() - t0) * 1000 / len(keys)


def start_moto(port: int, log: Path, bucket: str = "bench") -> subprocess.Popen:
    """A moto S3 server on 127.0.0.1:`port` logging to `log`, with `bucket` created; returns
    once it answers (also `benchmarks/scale.py --full --store-url s3://...`)."""
    with open(log, "wb") as out:  # werkzeug logs one line per request: the request count
        proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p",
                                 str(port)], stdout=out, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while True:
        try:
            urllib.request.urlopen(urllib.request.Request(
                f"http://127.0.0.1:{port}/{bucket}", method="PUT"), timeout=5)
            return proc
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                raise SystemExit("moto's S3 server did not start (pip install 'moto[server]')")
            time.sleep(0.2)


def served_requests(log: Path) -> int:
    """HTTP requests the moto server logging to `log` has answered: its own access log, a count
    independent of embody's code."""
    return sum(1 for line in log.read_text(errors="replace").splitlines()
               if " HTTP/1.1\" " in line)


def _run_requests(sequences: int, work: Path, served) -> float:
    """Requests per sequence of one `embody run` over the synthetic set on the S3 store."""
    before = served()
    done = subprocess.run(
        [sys.executable, "-m", "embody.cli", "run", "--store", "s3://bench/run", "--limit",
         str(sequences), "--json", "--no-progress", "--critic", "none", "--no-render",
         "--workers", "1", "--set", "collision.enabled=false", "--set", "ik.iterations=1",
         "--set", "ik.shape_iterations=10", "--set", "run.report=false",
         "--set", f"run.synth_n={sequences}"],
        env={**os.environ, "EMBODY_WORK_DIR": str(work / "work")}, capture_output=True,
        text=True, cwd=Path(__file__).resolve().parents[1])
    if done.returncode != 0:
        raise SystemExit(f"embody run failed ({done.returncode}): {done.stderr[-800:]}")
    time.sleep(0.5)
    return (served() - before) / sequences


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=40, help="artifacts per store")
    ap.add_argument("--frames", type=int, default=150, help="frames per artifact")
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds per store")
    ap.add_argument("--run-sequences", type=int, default=2,
                    help="sequences of the `embody run` whose requests are counted (0: none)")
    args = ap.parse_args()

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    os.environ.update(AWS_ENDPOINT_URL=f"http://127.0.0.1:{port}", AWS_ACCESS_KEY_ID="bench",
                      AWS_SECRET_ACCESS_KEY="bench", AWS_REGION="us-east-1")
    work = Path(tempfile.mkdtemp(prefix="embody-objbench-"))
    log = work / "moto.log"
    proc = start_moto(port, log)

    def served() -> int:
        return served_requests(log)
    try:
        from embody.store import ArtifactStore

        rng = np.random.default_rng(0)
        arrays = [_artifact(rng, args.frames) for _ in range(args.n)]
        rounds = {"local": [], "s3": []}
        for r in range(args.rounds):  # alternate, best round of each: the machine is shared
            with tempfile.TemporaryDirectory() as tmp:
                keys = [uuid.uuid4().hex * 2 for _ in range(args.n)]
                rounds["local"].append(_cycle(ArtifactStore(tmp), keys, arrays))
            keys = [uuid.uuid4().hex * 2 for _ in range(args.n)]
            store = ArtifactStore(f"s3://bench/r{r}")
            before = served()
            rounds["s3"].append(_cycle(store, keys, arrays))
            time.sleep(0.5)  # the server's log lines of the last requests
            requests = (served() - before) / args.n
        local, s3 = min(rounds["local"]), min(rounds["s3"])
        print(f"local {local:.2f} ms/artifact, s3 (moto, localhost) {s3:.2f} ms/artifact, "
              f"{requests:.1f} requests/artifact")
        per_seq = ""
        if args.run_sequences:
            cold, warm = (_run_requests(args.run_sequences, work, served) for _ in range(2))
            print(f"embody run of {args.run_sequences} sequences: {cold:.0f} requests/sequence "
                  f"cold, {warm:.0f} warm")
            per_seq = f" requests_per_sequence={cold:.0f} warm_requests_per_sequence={warm:.0f}"
        print(f"RESULT local_ms={local:.2f} s3_ms={s3:.2f} overhead_ratio={s3 / local:.2f} "
              f"requests_per_artifact={requests:.1f}{per_seq} n={args.n} frames={args.frames}")
    finally:
        proc.terminate()
        proc.wait()
        import shutil
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
