"""A run's identities on a shared network (`derl certs`): a CA, one certificate per node of a
launch file (common name = its node id) and each node's Zenoh config: mutual TLS, and access
control that lets each certificate publish only on its own node's keys. A Slurm job issues its
nodes' identities at each start with the user's CA (`load_ca`, `issue_identities`).

The rules come from the key layout (`messages.keys`): a worker's keys carry its node id
(``fitness/<node>/<child>``), so the certificate of ``gpu1-trainer-3`` may put on
``derl/<run>/fitness/gpu1-trainer-3/*`` (and, after restarts, ``gpu1-trainer-3.r<n>``), never
on another trainer's keys; only the coordinator's certificate gives jobs, acks and births; a
monitor's certificate may subscribe and query, and nothing it publishes is delivered; any other
certificate of the CA gets nothing (default deny). Every node holds the same rules and checks
what it receives (ingress), so a router or a peer drops a forgery before it is forwarded.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from derl.messages.keys import ARITY, PUBLISHERS, ROOT
from derl.nodes.launch.commands import NODE_CONFIG, NodeCommand, build_commands
from derl.nodes.launch.model import LaunchFile, RouterTopology, split_endpoint

MONITOR = "derl-monitor"  # the common name of the monitors' certificate
VALID_DAYS = 365
TAKE_PART = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query"]
DELIVER = [*TAKE_PART, "put", "delete", "liveliness_token", "declare_queryable", "reply"]


def write_identities(launch: LaunchFile, out: Path) -> list[Path]:
    """A new CA (``ca.pem``, ``ca.key``) and the identities `issue_identities` writes with it;
    the configs."""
    out.mkdir(parents=True, exist_ok=True)
    return issue_identities(launch, out, *make_ca(out, f"derl {launch.run} CA"))


def issue_identities(
    launch: LaunchFile, out: Path, ca_key: ec.EllipticCurvePrivateKey, ca: x509.Certificate
) -> list[Path]:
    """The CA's certificate (``ca.pem``) and, for every node of `launch` and for a monitor, a
    folder ``<name>/`` with ``node.pem``, ``node.key`` (signed by the CA) and its Zenoh config;
    the configs."""
    out.mkdir(parents=True, exist_ok=True)
    _write(out / "ca.pem", ca.public_bytes(serialization.Encoding.PEM))
    nodes = [c for c in build_commands(launch) if c.role != "ssh"]
    access = access_control(launch.run, nodes)
    configs = []
    for command in nodes:
        folder = out / command.name
        names = _host_names(launch, command.host)
        issue(ca_key, ca, command.name, names, folder)
        configs.append(_write_config(folder, out, access, mode=None))
    issue(ca_key, ca, MONITOR, ["localhost", "127.0.0.1"], out / MONITOR)
    configs.append(_write_config(out / MONITOR, out, access, mode="client"))
    return configs


def make_ca(out: Path, name: str) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A new CA in `out` (``ca.pem``, and ``ca.key``, which stays with whoever signs)."""
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    cert = (
        _builder(subject, subject, key.public_key())
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .sign(key, hashes.SHA256())
    )
    _write(out / "ca.pem", cert.public_bytes(serialization.Encoding.PEM))
    _write(out / "ca.key", _private(key), secret=True)
    return key, cert


def load_ca(folder: Path) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """The CA that `make_ca` wrote in `folder` (``ca.key``, ``ca.pem``); ValueError saying what
    is missing or not an EC key."""
    try:
        key = serialization.load_pem_private_key((folder / "ca.key").read_bytes(), None)
        cert = x509.load_pem_x509_certificate((folder / "ca.pem").read_bytes())
    except (OSError, ValueError) as error:
        raise ValueError(f"{folder} holds no `derl certs` CA (ca.key, ca.pem): {error}") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ValueError(f"{folder / 'ca.key'} is not the EC key of a `derl certs` CA")
    return key, cert


def issue(
    ca_key: ec.EllipticCurvePrivateKey,
    ca: x509.Certificate,
    name: str,
    addresses: list[str],
    folder: Path,
) -> None:
    """``folder/node.pem`` and ``node.key``: a certificate for `name` (its common name), valid
    for `addresses` (IPs or DNS names others connect to), signed by the CA."""
    key = ec.generate_private_key(ec.SECP256R1())
    alt: list[x509.GeneralName] = []
    for address in dict.fromkeys(addresses):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(address)))
        except ValueError:
            alt.append(x509.DNSName(address))
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    cert = (
        _builder(subject, ca.subject, key.public_key())
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
            ),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    folder.mkdir(parents=True, exist_ok=True)
    _write(folder / "node.pem", cert.public_bytes(serialization.Encoding.PEM))
    _write(folder / "node.key", _private(key), secret=True)


def access_control(run: str, nodes: list[NodeCommand]) -> dict[str, object]:
    """Zenoh's `access_control` section: one subject per node (its common name), allowed to
    put only on its role's keys that carry its own node id; monitors may listen and query."""
    rules: list[dict[str, object]] = [
        _rule("take-part", "ingress", TAKE_PART, [f"{ROOT}/**"]),
        _rule("deliver", "egress", DELIVER, [f"{ROOT}/**"]),
    ]
    subjects = [{"id": MONITOR, "cert_common_names": [MONITOR]}]
    policies = [{"id": MONITOR, "subjects": [MONITOR], "rules": ["take-part", "deliver"]}]
    for node in nodes:
        own = f"own-{node.name}"
        rules.append(_rule(own, "ingress", _messages(node.role), own_keys(run, node)))
        subjects.append({"id": node.name, "cert_common_names": [node.name]})
        policies.append(
            {"id": node.name, "subjects": [node.name], "rules": ["take-part", "deliver", own]}
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def own_keys(run: str, node: NodeCommand) -> list[str]:
    """The key expressions `node` may publish on: a worker, its role's kinds (`PUBLISHERS`)
    where the first id segment is one of its ids (`_me`); the coordinator
    and a router, the whole run: they forward what their clients (monitors, nodes behind a
    router) publish, which passed their own check when it came in."""
    if node.role in ("coordinator", "router"):
        return [f"{ROOT}/{run}/**"]
    keys = []
    for kind, roles in PUBLISHERS.items():
        if node.role not in roles:
            continue
        if kind == "alive":  # alive/<role>/<node>
            keys += [f"{ROOT}/{run}/alive/{node.role}/{me}" for me in _me(node)]
        else:
            rest = ["*"] * (ARITY[kind] - 1)
            keys += ["/".join([ROOT, run, kind, me, *rest]) for me in _me(node)]
    return keys


def _me(node: NodeCommand) -> list[str]:
    """`node`'s ids: its own and its restarts' (``<id>.r1`` ... up to its `max_restarts`), no
    other (a wildcard let one certificate name itself ``<id>.r901`` or ``<id>.rX-evil``)."""
    return [node.name, *(f"{node.name}.r{n}" for n in range(1, node.max_restarts + 1))]


def _messages(role: str) -> list[str]:
    if role in ("coordinator", "router"):
        return ["put", "delete", "liveliness_token", "declare_queryable", "reply"]
    return ["put", "liveliness_token"]


def _rule(id: str, flow: str, messages: list[str], keys: list[str]) -> dict[str, object]:
    return {
        "id": id,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": keys,
    }


def _write_config(folder: Path, out: Path, access: dict[str, object], mode: str | None) -> Path:
    """A node's Zenoh config: mutual TLS with its certificate, the run's access control."""
    pem, key, ca = (str((p).resolve()) for p in (folder / "node.pem", folder / "node.key",
                                                  out / "ca.pem"))  # fmt: skip
    tls = {
        "root_ca_certificate": ca,
        "enable_mtls": True,
        "listen_certificate": pem,
        "listen_private_key": key,
        "connect_certificate": pem,
        "connect_private_key": key,
        "verify_name_on_connect": True,
    }
    config: dict[str, object] = {
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tls": tls}},
        "access_control": access,
    }
    if mode is not None:
        config["mode"] = mode
    path = folder / NODE_CONFIG
    _write(path, (json.dumps(config, indent=2) + "\n").encode())
    return path


def _host_names(launch: LaunchFile, host_name: str) -> list[str]:
    """The names others may reach a node of this host by (its address, where it listens; the
    router's endpoint on the router's host), and loopback."""
    host = launch.host(host_name)
    names = [host.address]
    if host.listen:
        names.append(split_endpoint(host.listen)[1])
    topology = launch.topology
    if isinstance(topology, RouterTopology) and topology.host == host_name:
        names.append(split_endpoint(topology.endpoint)[1])
    wildcard = {"0.0.0.0", "[::]", "::"}
    return [name for name in [*names, "localhost", "127.0.0.1"] if name not in wildcard]


def _builder(subject: x509.Name, issuer: x509.Name, public_key) -> x509.CertificateBuilder:
    now = datetime.datetime.now(datetime.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(issuer)
        .public_key(public_key)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
    )


def _private(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _write(path: Path, data: bytes, secret: bool = False) -> None:
    path.write_bytes(data)
    if secret:
        os.chmod(path, 0o600)
