"""DDS Security (SROS2) with a keystore made by ``openssl`` alone (no ``ros2 security`` CLI).

The keystore holds what rmw expects per enclave (``<keystore>/enclaves/<enclave>/``:
identity_ca.cert.pem, cert.pem, key.pem, permissions_ca.cert.pem, governance.p7s,
permissions.p7s); the governance protects every topic and refuses unauthenticated participants.
A talker runs with ``ROS_SECURITY_ENABLE=true``, ``ROS_SECURITY_STRATEGY=Enforce``.

Either the middleware secures the topic (a secured listener receives, an unsecured one receives
nothing), or it refuses to start the secured process: it must never run it unsecured. The Fast
DDS of the PyPI wheels (``ros-fastrtps`` 2.14, built without ``-DSECURITY=ON``) does the latter:
node creation fails with "This Fast DDS version doesn't have the security libraries"
(docs/security.md); robots are then authenticated by the application (hmrta.keys).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

NO_SECURITY = "doesn't have the security libraries"
DOMAINS = "<domains><id_range><min>0</min><max>232</max></id_range></domains>"

GOVERNANCE = f"""<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_governance.xsd">
  <domain_access_rules>
    <domain_rule>
      {DOMAINS}
      <allow_unauthenticated_participants>false</allow_unauthenticated_participants>
      <enable_join_access_control>true</enable_join_access_control>
      <discovery_protection_kind>ENCRYPT</discovery_protection_kind>
      <liveliness_protection_kind>ENCRYPT</liveliness_protection_kind>
      <rtps_protection_kind>SIGN</rtps_protection_kind>
      <topic_access_rules>
        <topic_rule>
          <topic_expression>*</topic_expression>
          <enable_discovery_protection>true</enable_discovery_protection>
          <enable_liveliness_protection>true</enable_liveliness_protection>
          <enable_read_access_control>true</enable_read_access_control>
          <enable_write_access_control>true</enable_write_access_control>
          <metadata_protection_kind>ENCRYPT</metadata_protection_kind>
          <data_protection_kind>ENCRYPT</data_protection_kind>
        </topic_rule>
      </topic_access_rules>
    </domain_rule>
  </domain_access_rules>
</dds>
"""

PERMISSIONS = """<?xml version="1.0" encoding="UTF-8"?>
<dds xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" xsi:noNamespaceSchemaLocation="http://www.omg.org/spec/DDS-SECURITY/20170901/omg_shared_ca_permissions.xsd">
  <permissions>
    <grant name="{enclave}">
      <subject_name>CN={enclave}</subject_name>
      <validity><not_before>2020-01-01T00:00:00</not_before><not_after>2099-01-01T00:00:00</not_after></validity>
      <allow_rule>
        {domains}
        <publish><topics><topic>*</topic></topics></publish>
        <subscribe><topics><topic>*</topic></topics></subscribe>
      </allow_rule>
      <default>DENY</default>
    </grant>
  </permissions>
</dds>
"""

NODE = textwrap.dedent("""
    import json, sys, time
    import rclpy
    from std_msgs.msg import String

    role, seconds = sys.argv[1], float(sys.argv[2])
    rclpy.init(args=sys.argv)
    try:
        node = rclpy.create_node(role + "_node")
    except Exception as e:
        print("CREATE FAILED: " + str(e), flush=True)
        sys.exit(3)
    got = []
    if role == "talker":
        pub = node.create_publisher(String, "secret_chatter", 10)
    else:
        node.create_subscription(String, "secret_chatter", lambda m: got.append(m.data), 10)
    end, n = time.monotonic() + seconds, 0
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
        if role == "talker":
            n += 1
            pub.publish(String(data=f"secret {n}"))
    print("RESULT " + json.dumps({"role": role, "sent": n, "received": len(got)}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
""")


def _openssl(*args: str, cwd: Path) -> None:
    r = subprocess.run(["openssl", *args], check=False, cwd=cwd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, f"openssl {' '.join(args)}: {r.stderr.strip()}"


def make_sros2_keystore(root: Path, enclaves: list[str]) -> Path:
    """An SROS2 keystore made with openssl: one CA (identity and permissions), a governance
    protecting every topic, and per enclave a certificate (CN=<enclave>) and signed permissions."""
    (root / "public").mkdir(parents=True)
    (root / "private").mkdir(mode=0o700)
    _openssl("ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", "private/ca.key.pem", cwd=root)
    _openssl("req", "-x509", "-new", "-key", "private/ca.key.pem", "-subj", "/CN=hmrta_test_ca", "-days", "3650",
             "-sha256", "-out", "public/ca.cert.pem", cwd=root)
    (root / "governance.xml").write_text(GOVERNANCE)
    _openssl("smime", "-sign", "-text", "-in", "governance.xml", "-out", "governance.p7s",
             "-signer", "public/ca.cert.pem", "-inkey", "private/ca.key.pem", cwd=root)
    for enclave in enclaves:
        d = root / "enclaves" / enclave.strip("/")
        d.mkdir(parents=True)
        rel = os.path.relpath(d, root)
        _openssl("ecparam", "-name", "prime256v1", "-genkey", "-noout", "-out", f"{rel}/key.pem", cwd=root)
        _openssl("req", "-new", "-key", f"{rel}/key.pem", "-subj", "/CN=" + enclave.replace("/", "\\/"),
                 "-out", f"{rel}/req.csr", cwd=root)
        _openssl("x509", "-req", "-in", f"{rel}/req.csr", "-CA", "public/ca.cert.pem", "-CAkey", "private/ca.key.pem",
                 "-CAcreateserial", "-days", "3650", "-sha256", "-out", f"{rel}/cert.pem", cwd=root)
        for name in ("identity_ca.cert.pem", "permissions_ca.cert.pem"):
            shutil.copy(root / "public" / "ca.cert.pem", d / name)
        shutil.copy(root / "governance.p7s", d / "governance.p7s")
        (d / "permissions.xml").write_text(PERMISSIONS.format(enclave=enclave, domains=DOMAINS))
        _openssl("smime", "-sign", "-text", "-in", f"{rel}/permissions.xml", "-out", f"{rel}/permissions.p7s",
                 "-signer", "public/ca.cert.pem", "-inkey", "private/ca.key.pem", cwd=root)
        # the documents verify against the permissions CA, the certificate against the identity CA
        _openssl("smime", "-verify", "-in", f"{rel}/permissions.p7s", "-CAfile", "public/ca.cert.pem",
                 "-out", os.devnull, cwd=root)
        _openssl("verify", "-CAfile", "public/ca.cert.pem", f"{rel}/cert.pem", cwd=root)
    _openssl("smime", "-verify", "-in", "governance.p7s", "-CAfile", "public/ca.cert.pem", "-out", os.devnull,
             cwd=root)
    return root


def _start(script: Path, role: str, seconds: float, env: dict[str, str], enclave: str | None) -> subprocess.Popen:
    args = [sys.executable, str(script), role, str(seconds)]
    if enclave:
        args += ["--ros-args", "--enclave", enclave]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            stdin=subprocess.DEVNULL)


def _finish(p: subprocess.Popen, timeout: float) -> tuple[int, str, dict | None]:
    try:
        out, _ = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        out, _ = p.communicate(timeout=10)
    res = [json.loads(line[7:]) for line in out.splitlines() if line.startswith("RESULT ")]
    return p.returncode, out, (res[-1] if res else None)


def test_sros2_enforce_secures_the_topic_or_refuses_to_start(tmp_path, domain):
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed: it makes the SROS2 keystore")
    ks = make_sros2_keystore(tmp_path / "keystore", ["/talker", "/listener"])
    script = tmp_path / "node.py"
    script.write_text(NODE)
    plain = {k: v for k, v in os.environ.items() if not k.startswith("ROS_SECURITY_")}
    plain.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                 ROS_LOG_DIR=str(tmp_path / "ros_logs"))
    secure = dict(plain, ROS_SECURITY_KEYSTORE=str(ks), ROS_SECURITY_ENABLE="true", ROS_SECURITY_STRATEGY="Enforce")

    eavesdropper = _start(script, "listener", 6.0, plain, None)
    talker = _start(script, "talker", 5.0, secure, "/talker")
    listener = None
    try:
        try:
            talker.wait(timeout=3.0)  # a middleware without security refuses at once
        except subprocess.TimeoutExpired:
            pass
        if talker.poll() is not None:
            rc, out, _ = _finish(talker, 10)
            assert rc != 0 and "CREATE FAILED" in out, out
            assert NO_SECURITY in out, f"the secured talker failed for another reason:\n{out}"
            rc, out, res = _finish(eavesdropper, 30)
            assert rc == 0 and res is not None, out
            assert res["received"] == 0  # nothing was published unsecured
            print(f"DDS Security unavailable in this middleware; the secured talker refused to start: "
                  f"{NO_SECURITY}")
            return
        listener = _start(script, "listener", 4.0, secure, "/listener")
        rc, out, res = _finish(listener, 60)
        assert rc == 0 and res is not None, out
        assert res["received"] > 0, "the secured listener received nothing from the secured talker"
        rc, out, talked = _finish(talker, 60)
        assert rc == 0 and talked["sent"] > 0, out
        rc, out, heard = _finish(eavesdropper, 60)
        assert rc == 0 and heard is not None, out
        assert heard["received"] == 0, "an unsecured process read a protected topic"
    finally:
        for p in (talker, eavesdropper, listener):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait(timeout=10)
