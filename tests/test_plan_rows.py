"""What a plan server's rows cost on the wire (docs/delivery.md, "The wire"): a real ``v2v-serve`` on
127.0.0.1, read by ``V2VStreamDataset`` and by a bare socket, the bytes counted by a TCP proxy
between them. A padding row (past the epoch's end, or a window the decode did not give) costs no
payload, and a fetch whose batch would pass the batch limit is refused in one line."""
from __future__ import annotations

import hashlib
import socket
import threading

import zmq

from harness.serve import ServeProcess
from v2v_client import V2VStreamDataset
from v2v_wire.plan_messages import Fetch, PlanAsk, plan_server_message
from v2v_wire.protocol import pack, unpack

#: 41-frame windows, one sample a clip: the bundled clips' epoch is 4 samples, cheap to decode
ARGS = ["--sequence-length", "8", "--crop-size", "32", "--max-samples-per-video", "1",
        "--flow-preset", "ultrafast", "--workers", "1", "--shuffle-buffer", "2", "--batch-size", "3"]
OUTPUTS = ("voxels", "frames")


class CountingProxy:
    """A TCP proxy from a free port on 127.0.0.1 to ``port``: ``down`` counts the bytes the server
    sent its readers, through every connection."""

    def __init__(self, port: int):
        self.target, self.down = port, 0
        self.lock = threading.Lock()
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = f"tcp://127.0.0.1:{self.listener.getsockname()[1]}"
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(("127.0.0.1", self.target))
            threading.Thread(target=self._pipe, args=(client, server, False), daemon=True).start()
            threading.Thread(target=self._pipe, args=(server, client, True), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket, count: bool) -> None:
        try:
            while True:
                data = src.recv(1 << 16)
                if not data:
                    break
                if count:
                    with self.lock:
                        self.down += len(data)
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass

    def close(self) -> None:
        self.listener.close()


def read(endpoint: str):
    """(sample id or None, padding, digest of each output's row) of one epoch's rows, batches of 3."""
    rows = []
    for b in V2VStreamDataset(endpoint, 3, outputs=OUTPUTS, timeout_s=120, prefetch=2):
        for j, sid in enumerate(b["sample_ids"]):
            rows.append((sid, bool(b["padding"][j]),
                         tuple(hashlib.sha1(b[o][j].numpy().tobytes()).hexdigest() for o in OUTPUTS)))
            if b["padding"][j]:
                assert not any(b[o][j].any() for o in OUTPUTS)  # padding rows are zeros
    return rows


def ask(endpoint: str, fetch_of):
    """Send a bare socket's ``plan_ask``, then ``fetch_of(plan identity)``: the answer and its frames."""
    ctx = zmq.Context()
    sock = ctx.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    try:
        sock.send(pack(PlanAsk().to_wire()))
        assert sock.poll(60000)
        info = plan_server_message(unpack(sock.recv_multipart()[0]))
        sock.send(pack(fetch_of(info.plan).to_wire()))
        assert sock.poll(120000)
        frames = sock.recv_multipart()
        return plan_server_message(unpack(frames[0])), frames[1:]
    finally:
        sock.close()
        ctx.term()


def test_padding_rows_cost_no_payload_and_the_batches_are_the_same(tmp_path):
    with ServeProcess(ARGS + ["--cache-dir", str(tmp_path / "cache")], ready_timeout_s=120) as srv:
        direct = read(srv.endpoint)
        proxy = CountingProxy(int(srv.endpoint.rsplit(":", 1)[1]))
        try:
            through = read(proxy.endpoint)
            epoch = proxy.down
            proxy.down = 0
            past, frames = ask(proxy.endpoint, lambda plan: Fetch(1, 0, 1000, 1128, OUTPUTS, plan))
            answered = proxy.down
            whole, payload = ask(proxy.endpoint, lambda plan: Fetch(2, 0, 0, 4, OUTPUTS, plan))
        finally:
            proxy.close()
    samples = [r for r in direct if not r[1]]
    assert through == direct and len(samples) == 4 and len({r[0] for r in samples}) == 4
    assert sum(r[1] for r in direct) == 2  # 2 steps of 3 rows: the epoch's 4 samples and 2 padding rows
    assert whole.padding == [False] * 4
    row_bytes = sum(len(f) for f in payload) / 4  # one sample's voxels and frames on the wire
    # the epoch's 2 steps and the 2 fetches a reader asks ahead past its end: the 4 samples' payload
    # and headers, not 12 rows' (6 of them padding)
    assert 4 * row_bytes <= epoch < 5 * row_bytes, (epoch, row_bytes)
    assert past.padding == [True] * 128 and past.sample_ids == [None] * 128
    assert sum(len(f) for f in frames) == 0 and answered < 16 * 1024, answered  # 128 rows past the end: headers only
    assert all(s["shape"][0] == 0 for s in past.arrays)


def test_a_fetch_whose_batch_would_pass_the_batch_limit_is_refused_in_one_line(tmp_path):
    """At the paper's shapes (the default recipe), 4,096 rows of voxels pass 2 GiB: refused before
    anything is decoded; 64 rows are not."""
    with ServeProcess(["--workers", "1", "--cache-dir", str(tmp_path / "cache")],
                      ready_timeout_s=120) as srv:
        refused, _ = ask(srv.endpoint, lambda plan: Fetch(7, 0, 0, 4096, ("voxels", "frames", "flow"), plan))
    assert refused.request == 7 and refused.code == "too_big" and "\n" not in refused.message
    assert refused.message.startswith("fetch of 4096 rows: its ") and "over the batch limit of 2147483648" in \
        refused.message, refused.message


def test_more_epochs_read_at_once_than_plans_kept_build_each_plan_once(tmp_path, videos):
    """A reader of each of ``PLANS_KEPT + 1`` epochs, at once: each reads its whole epoch, every
    sample once, and the server builds each epoch's plan once (its stop line), not one for each
    pending fetch in each loop turn."""
    import re
    import shutil

    from v2v_server.delivery.plan_schedule import PLANS_KEPT

    corpus = tmp_path / "corpus"
    corpus.mkdir()
    for name in ("bikes.mp4", "bigbuckbunny.mp4"):
        shutil.copyfile(videos / name, corpus / name)
    epochs = PLANS_KEPT + 1
    got = {}

    def job(epoch: int) -> None:
        ds = V2VStreamDataset(srv.endpoint, 1, outputs=("voxels",), timeout_s=120, prefetch=1)
        ds.set_epoch(epoch)
        got[epoch] = [sid for b in ds for sid, pad in zip(b["sample_ids"], b["padding"].tolist()) if not pad]

    with ServeProcess(ARGS + ["--videos", str(corpus), "--cache-dir", str(tmp_path / "cache"), "--log-level", "info"],
                      ready_timeout_s=120) as srv:
        threads = [threading.Thread(target=job, args=(e,)) for e in range(epochs)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(180)
    assert sorted(got) == list(range(epochs))
    assert all(len(ids) == 2 and sorted(ids) == sorted(got[0]) for ids in got.values())
    assert len({tuple(ids) for ids in got.values()}) > 1  # each epoch its own order
    built = re.search(r"(\d+) epoch plan\(s\) built", srv.log)
    assert built is not None and epochs <= int(built.group(1)) <= epochs + 1, srv.log[-2000:]
