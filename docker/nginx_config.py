"""Render docker/nginx.conf.template for a set of replicas, inside Docker or outside it (no dependencies).

    python docker/nginx_config.py --replica 127.0.0.1:8765 --replica 127.0.0.1:8766 --listen 8080 > nginx.conf
    python docker/nginx_config.py ... --tls-listen 8443 --tls-cert cert.pem --tls-key key.pem --prefix /tmp/ngx
    nginx -p /tmp/ngx -c /path/to/nginx.conf

``--prefix`` adds a pid file, logs and temp folders under that folder, so that nginx runs unprivileged.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

TEMPLATE = Path(__file__).with_name("nginx.conf.template")


def render(
    replicas: list[str],
    listen: str | None = "8080",
    tls: tuple[str, str, str] | None = None,
    prefix: str | None = None,
    max_fails: int = 1,
    fail_timeout_s: int = 5,
) -> str:
    """The nginx.conf text. replicas: HOST:PORT each; listen: plain ws:// port or address:port (None: none);
    tls: (listen, certificate chain, key) to terminate wss:// at nginx; prefix: a folder for pid and logs."""
    servers = "\n".join(
        f"        server {r} max_fails={max_fails} fail_timeout={fail_timeout_s}s;" for r in replicas
    )
    lines = [f"        listen {listen};"] if listen is not None else []
    if tls is not None:
        tls_listen, cert, key = tls
        lines += [
            f"        listen {tls_listen} ssl;",
            f"        ssl_certificate {cert};",
            f"        ssl_certificate_key {key};",
        ]
    listen_lines = "\n".join(lines)
    glob = f"pid {prefix}/nginx.pid;\nerror_log {prefix}/error.log;" if prefix is not None else ""
    # Only the template's three names are replaced (as `envsubst '$UPSTREAM_SERVERS $LISTEN $GLOBAL'` does):
    # nginx's own $variables stay as they are.
    text = TEMPLATE.read_text()
    for name, value in (("UPSTREAM_SERVERS", servers), ("LISTEN", listen_lines), ("GLOBAL", glob)):
        text = text.replace("${" + name + "}", value)
    if prefix is not None:  # temp folders live in the http block
        temp = "".join(
            f"    {kind}_temp_path {prefix}/{kind}_temp;\n"
            for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")
        )
        text = text.replace("http {\n", f"http {{\n    access_log off;\n{temp}", 1)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--replica", action="append", required=True, metavar="HOST:PORT")
    parser.add_argument("--listen", default="8080", help="plain port or address:port (default 8080)")
    parser.add_argument(
        "--tls-listen", help="port or address:port for wss:// (needs --tls-cert and --tls-key)"
    )
    parser.add_argument("--tls-cert", help="certificate chain (PEM): terminate wss:// at nginx")
    parser.add_argument("--tls-key", help="its key (PEM)")
    parser.add_argument("--prefix", help="folder for pid, logs and temp files (running outside Docker)")
    args = parser.parse_args(argv)
    if len({bool(args.tls_listen), bool(args.tls_cert), bool(args.tls_key)}) > 1:
        parser.error("--tls-listen, --tls-cert and --tls-key go together")
    tls = (args.tls_listen, args.tls_cert, args.tls_key) if args.tls_cert else None
    sys.stdout.write(render(args.replica, args.listen, tls, args.prefix))
    return 0


if __name__ == "__main__":
    sys.exit(main())
