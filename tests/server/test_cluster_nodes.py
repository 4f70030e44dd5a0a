"""Two Ray nodes on one machine (ray.cluster_utils.Cluster): scene replicas spread over both nodes and a
client on the head's gRPC port is answered by either, as by one process."""

from __future__ import annotations

import os
from pathlib import Path

import grpc
import pytest

from fmgs_server.cluster.app import REPLICA_KEY
from fmgs_server.cluster.config import ClusterConfig
from fmgs_server.config import ServerConfig
from fmgs_server.server import start_server
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2 as pb
from fmgs_wire.proto.fmgs.v1 import fmgs_pb2_grpc as pb_grpc
from tests.helpers.query_scenes import CLASS_NAMES, FakeEncoder, blob_scene

ray = pytest.importorskip("ray", reason="the fmgs[ray] extra is part of the CI install")
ROOT = Path(__file__).resolve().parents[2]


def encoder_factory(encoder_id: str):
    return FakeEncoder()


def test_replicas_on_two_nodes_answer_alike(tmp_path):
    from ray import serve
    from ray.cluster_utils import Cluster

    from fmgs_server.cluster.launch import start_ray_serve

    models = tmp_path / "models"
    models.mkdir()
    for i in range(4):
        blob_scene(models / f"scene{i}", seed=i)
    env = {"env_vars": {"PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}}
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)  # a second raylet: another node as far as Ray's scheduler knows
    try:
        ray.init(address=cluster.address, runtime_env=env, log_to_driver=False)
        cfg = ServerConfig(models=models, port=0, reload_check_s=0.0)
        cc = ClusterConfig(min_replicas=2, max_replicas=2, replica_cpus=1.0)  # one per node: 1 CPU each
        port = start_ray_serve(cfg, cc, cluster.address, encoder_factory)
        details = serve.context._get_global_client().get_serve_details()
        replicas = details["applications"]["fmgs"]["deployments"]["SceneHost"]["replicas"]
        assert len({r["node_id"] for r in replicas}) == 2  # spread over both nodes
        direct = start_server(cfg, encoder_factory=encoder_factory)
        stub = pb_grpc.FmgsStub(grpc.insecure_channel(f"127.0.0.1:{port}"))
        one = pb_grpc.FmgsStub(grpc.insecure_channel(direct.address))
        seen = set()
        for i in range(4):
            req = pb.TextQueryRequest(scene=f"scene{i}", texts=list(CLASS_NAMES), top_k=20)
            call = stub.TextQuery(req, timeout=120)
            got = [(c.text_index, c.index.data, c.relevancy.data) for c in call]
            seen |= {v for k, v in call.trailing_metadata() if k == REPLICA_KEY}
            want = [(c.text_index, c.index.data, c.relevancy.data) for c in one.TextQuery(req, timeout=120)]
            assert got == want and len(got) >= 3
        direct.stop(0)
        assert len(seen) == 2  # scenes go to the replica holding the fewest: both nodes answer
    finally:
        serve.shutdown()
        ray.shutdown()
        cluster.shutdown()
