"""The Kubernetes example is schema-valid (kubernetes-validate, strict) and routes as docker/README.md says."""

from pathlib import Path

import kubernetes_validate
import pytest
import yaml

MANIFEST = Path(__file__).resolve().parents[1] / "docker" / "k8s.yaml"


def test_every_resource_is_valid_against_the_kubernetes_schema():
    resources = [r for r in yaml.safe_load_all(MANIFEST.read_text()) if r]
    assert [r["kind"] for r in resources] == ["Deployment", "Service", "Ingress"]
    for resource in resources:
        kubernetes_validate.validate(resource, kubernetes_validate.latest_version(), strict=True)


def test_sticky_by_session_and_probes_on_the_servers_endpoints():
    deployment, _, ingress = yaml.safe_load_all(MANIFEST.read_text())
    assert (
        ingress["metadata"]["annotations"]["nginx.ingress.kubernetes.io/upstream-hash-by"] == "$arg_session"
    )
    container = deployment["spec"]["template"]["spec"]["containers"][0]
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert container["livenessProbe"]["httpGet"]["path"] == "/healthz"


def test_a_broken_manifest_is_caught():
    deployment = next(yaml.safe_load_all(MANIFEST.read_text()))
    deployment["spec"]["replicas"] = "three"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(deployment, kubernetes_validate.latest_version(), strict=True)
