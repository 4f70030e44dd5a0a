"""deploy/kuberay/rayservice.yaml validates against the RayService CRD schema of the KubeRay release it
targets, as the API server would check it: unknown fields refused (kubectl's strict field validation),
int-or-string and preserve-unknown-fields honoured. The schema is KubeRay's own (tests/deploy/data/README.md).
"""

from __future__ import annotations

import copy
import gzip
import json
import re
from pathlib import Path

import pytest
import yaml

jsonschema = pytest.importorskip("jsonschema", reason="installed with ray[serve], part of the CI install")

ROOT = Path(__file__).resolve().parents[2]
MANIFEST = ROOT / "deploy/kuberay/rayservice.yaml"
KUBERAY = "v1.7.0"
SCHEMA = Path(__file__).parent / "data" / f"kuberay-{KUBERAY}-rayservice-v1.schema.json.gz"


def structural_to_jsonschema(node):
    """A Kubernetes structural schema as JSON Schema: objects with declared properties refuse others
    unless x-kubernetes-preserve-unknown-fields; x-kubernetes-int-or-string is integer or string."""
    if isinstance(node, list):
        return [structural_to_jsonschema(x) for x in node]
    if not isinstance(node, dict):
        return node
    out = {k: structural_to_jsonschema(v) for k, v in node.items() if not k.startswith("x-kubernetes-")}
    if node.get("x-kubernetes-int-or-string"):
        out.pop("type", None)
        out.setdefault("anyOf", [{"type": "integer"}, {"type": "string"}])
    preserve = node.get("x-kubernetes-preserve-unknown-fields", False)
    if node.get("type") == "object" and "properties" in node and "additionalProperties" not in node:
        if not preserve:
            out["additionalProperties"] = False
    return out


@pytest.fixture(scope="module")
def validator():
    raw = json.loads(gzip.decompress(SCHEMA.read_bytes()))
    assert (raw["group"], raw["kind"], raw["version"]) == ("ray.io", "RayService", "v1")
    schema = structural_to_jsonschema(raw["openAPIV3Schema"])
    cls = jsonschema.validators.validator_for({"$schema": "http://json-schema.org/draft-07/schema#"})
    return cls(schema)


def _rayservice() -> dict:
    docs = [d for d in yaml.safe_load_all(MANIFEST.read_text()) if d and d.get("kind") == "RayService"]
    assert len(docs) == 1
    return docs[0]


def _head(doc: dict) -> dict:
    return doc["spec"]["rayClusterConfig"]["headGroupSpec"]["template"]["spec"]


def _errors(validator, doc) -> list[str]:
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(doc)]


def test_the_manifest_names_the_kuberay_release_it_is_checked_against():
    assert _rayservice()["apiVersion"] == "ray.io/v1"
    assert re.search(rf"KubeRay {re.escape(KUBERAY)}\b", MANIFEST.read_text()), (
        f"rayservice.yaml should say it targets KubeRay {KUBERAY} (the schema this test holds)"
    )


def test_the_rayservice_validates_against_the_crd_schema(validator):
    errors = _errors(validator, _rayservice())
    assert not errors, "\n".join(errors[:20])


@pytest.mark.parametrize(
    ("where", "change"),
    [
        ("a misspelt field", lambda d: d["spec"].update(serveConfig=d["spec"].pop("serveConfigV2"))),
        ("a misspelt container field", lambda d: _head(d)["containers"][0].update(imagePolicy="Always")),
        (
            "replicas as a word",
            lambda d: d["spec"]["rayClusterConfig"]["workerGroupSpecs"][0].update(replicas="one"),
        ),
        (
            "a probe port as a list",
            lambda d: d["spec"]["rayClusterConfig"]["workerGroupSpecs"][0]["template"]["spec"]["containers"][
                0
            ]["readinessProbe"]["grpc"].update(port=[50051]),
        ),
        ("no head group", lambda d: d["spec"]["rayClusterConfig"].pop("headGroupSpec")),
    ],
)
def test_the_validation_catches_what_the_api_server_would_refuse(validator, where, change):
    doc = copy.deepcopy(_rayservice())
    change(doc)
    assert _errors(validator, doc), f"{where} passed the schema"


def test_int_or_string_quantities_and_preserved_fields_pass(validator):
    doc = copy.deepcopy(_rayservice())
    c = doc["spec"]["rayClusterConfig"]["headGroupSpec"]["template"]["spec"]["containers"][0]
    c["resources"]["limits"]["cpu"] = 2  # a quantity may be a number
    doc["spec"]["rayClusterConfig"]["headGroupSpec"]["template"]["metadata"]["annotations"] = {"a": "b"}
    assert not _errors(validator, doc)
