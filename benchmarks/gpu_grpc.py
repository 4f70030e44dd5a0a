"""The pose part's gRPC measurements: one call taken apart (server render, serialise, parse, decode, the
client's Python path), a bare echo of the same bytes as the transport's floor, and concurrent clients."""

from __future__ import annotations

import statistics
import time

from benchmarks.common import med_ms, proto_camera
from benchmarks.gpu_timing import timed


def grpc_breakdown(address: str, req, cam, frames: int, quick: bool) -> dict:
    """Where a served relevancy image's time goes, one client on loopback: the raw stub (unary Render),
    the same with the single-threaded unary-stream channel option, the thin client (its decode included),
    a pose stream (StreamRender, one client), the server's own render time, the response's encode and the
    client's decode, and a bare gRPC server echoing the same bytes (the transport's floor)."""
    import grpc
    import grpc.experimental

    from fmgs_client import CameraSpec, FmgsClient
    from fmgs_client.client import assemble_render
    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

    single = [(grpc.experimental.ChannelOptions.SingleThreadedUnaryStream, 1)]
    big = [("grpc.max_receive_message_length", 64 << 20)]
    out: dict = {}
    for tag, opts in (("", big), ("single_threaded_", big + single)):
        with grpc.insecure_channel(address, options=opts) as ch:
            stub = pb_grpc.FmgsStub(ch)
            for i in range(70):  # load, embed and cache every query text
                chunks = list(stub.Render(req(i)))
            ts, inner = [], []
            for _ in range(frames):
                t0 = time.perf_counter()
                chunks = list(stub.Render(req(0)))
                ts.append(time.perf_counter() - t0)
                inner.append(chunks[0].elapsed_ms)
            out[f"{tag}sequential_ms"] = med_ms(ts)
            out[f"{tag}sequential_images_per_s"] = 1e3 / med_ms(ts)
            out[f"{tag}server_render_ms"] = statistics.median(inner)
    out["response_bytes"] = sum(c.ByteSize() for c in chunks)
    out["response_chunks"] = len(chunks)
    out["client_decode_ms"] = med_ms(timed(lambda: assemble_render(chunks), frames, warm=2))
    payload = [c.SerializeToString() for c in chunks]
    out["client_parse_ms"] = med_ms(
        timed(lambda: [type(chunks[0]).FromString(b) for b in payload], frames, warm=2)
    )
    out["server_serialize_ms"] = med_ms(
        timed(lambda: [c.SerializeToString() for c in chunks], frames, warm=2)
    )
    out.update(echo_floor(payload, frames))
    # The thin client, as an integrator calls it.
    spec = CameraSpec.from_proto(proto_camera(cam))
    with FmgsClient(address, timeout=30) as client:
        for _ in range(3):
            client.render("pose", spec, text="q0")
        ts = timed(lambda: client.render("pose", spec, text="q0"), frames, warm=2)
        out["client_render_ms"] = med_ms(ts)
        out["client_render_images_per_s"] = 1e3 / med_ms(ts)
        # A pose stream: poses generated as fast as the client sends them; the server renders the newest.
        seconds = 2.0 if quick else 5.0
        got, t0 = 0, time.perf_counter()

        def poses():
            while time.perf_counter() - t0 < seconds:
                yield spec

        for _ in client.stream("pose", poses(), text="q0"):
            got += 1
        out["client_stream_images_per_s"] = got / (time.perf_counter() - t0)
    return out


def echo_floor(payload: list[bytes], frames: int) -> dict:
    """A bare gRPC server streaming back ``payload`` (a served answer's messages) to a unary-stream call:
    what the transport alone costs, without and with the single-threaded unary-stream option."""
    from concurrent import futures

    import grpc
    import grpc.experimental

    srv = grpc.server(futures.ThreadPoolExecutor(4), options=[("grpc.max_send_message_length", 64 << 20)])
    handler = grpc.unary_stream_rpc_method_handler(lambda r, c: iter(payload))
    srv.add_generic_rpc_handlers([grpc.method_handlers_generic_handler("echo.Echo", {"Get": handler})])
    port = srv.add_insecure_port("127.0.0.1:0")
    srv.start()
    out = {}
    try:
        single = [(grpc.experimental.ChannelOptions.SingleThreadedUnaryStream, 1)]
        for tag, opts in (("", []), ("single_threaded_", single)):
            opts = [*opts, ("grpc.max_receive_message_length", 64 << 20)]
            with grpc.insecure_channel(f"127.0.0.1:{port}", options=opts) as ch:
                call = ch.unary_stream("/echo.Echo/Get")
                out[f"{tag}echo_floor_ms"] = med_ms(timed(lambda c=call: list(c(b"")), frames, warm=5))
    finally:
        srv.stop(0)
    return out


def grpc_concurrent(address: str, req, clients: int, seconds: float) -> dict:
    """``clients`` threads, each with its own channel, send unary renders back to back for ``seconds``."""
    import threading

    import grpc

    from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc

    done, counts, errors = threading.Event(), [0] * clients, []

    def client(k: int) -> None:
        with grpc.insecure_channel(address) as ch:
            stub = pb_grpc.FmgsStub(ch)
            i = 0
            while not done.is_set():
                try:
                    list(stub.Render(req(i)))
                    counts[k] += 1
                except grpc.RpcError as e:
                    errors.append(e.code().name)
                i += 1

    th = [threading.Thread(target=client, args=(k,), daemon=True) for k in range(clients)]
    t0 = time.perf_counter()
    for t in th:
        t.start()
    time.sleep(seconds)
    done.set()
    for t in th:
        t.join(timeout=30)
    secs = time.perf_counter() - t0
    return {
        "grpc_concurrent_clients": clients,
        "grpc_concurrent_images_per_s": sum(counts) / secs,
        "grpc_concurrent_errors": len(errors),
    }


# ---------------------------------------------------------------- the paper's full render
