"""`vq-mitsuba ui`: a local web server for the editor page of one run.

Serves its own page (`ui/static`), the run's images under /run/, and a small JSON API over an
`EditorSession`. Binds to 127.0.0.1 unless a host is given. Nothing outside the page and the run
folder's images (and, for an edited run, the fitted run's) can be read, whatever the request says.

No other web page can drive it: a request whose `Host` (or `Origin`, when sent) is not an address
this server answers on is refused (so DNS rebinding reaches nothing), and every POST must be JSON
and carry the session's token, which only the served page holds (in its HTML, readable by
same-origin scripts only), in the `X-VQM-Token` header.
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import json
import math
import secrets
import signal
import socket
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

from vq_mitsuba.errors import InputError, UserError
from vq_mitsuba.ui.session import EditorSession

DEFAULT_HOST = "127.0.0.1"
STATIC = Path(__file__).resolve().parent / "static"
PAGES = {"/": ("index.html", "text/html; charset=utf-8"), "/index.html": ("index.html", "text/html; charset=utf-8"),
         "/app.js": ("app.js", "text/javascript; charset=utf-8"), "/style.css": ("style.css", "text/css; charset=utf-8")}
# What /run/ serves: images and maps only (never checkpoints, configuration or meshes).
TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".exr": "image/x-exr"}
MAX_BODY = 1 << 16
TOKEN_HEADER = "X-VQM-Token"
TOKEN_SLOT = "{{VQM_TOKEN}}"  # in index.html, replaced by the session's token
LOOPBACK = ("127.0.0.1", "localhost", "[::1]")
WILDCARD = ("", "0.0.0.0", "::")


def run_file(roots: list[Path], rel: str) -> Path | None:
    """The file `rel` (a URL path below /run/, still quoted) inside one of `roots`, or None when it
    is not a plain relative path to a file there."""
    rel = unquote(rel)
    parts = rel.split("/")
    if not rel or rel.startswith("/") or "\\" in rel or "\0" in rel or any(p in ("", ".", "..") for p in parts):
        return None
    if Path(rel).suffix.lower() not in TYPES:
        return None
    for root in roots:
        base = root.resolve()
        path = (base / rel).resolve()
        if path.is_relative_to(base) and path.is_file() and path.suffix.lower() in TYPES:
            return path
    return None


def finite_json(data):
    """`data` with every NaN or infinite float as None: the page parses strict JSON, which has no
    literal for them (a value that is not a number is shown as missing)."""
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {k: finite_json(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [finite_json(v) for v in data]
    return data


def _refuse_constant(name: str):
    raise InputError(None, f"the request body holds {name}, which is not a JSON number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise InputError(None, f"the request body holds {text}, which is beyond the range of a number")
    return value


def parse_body(raw: bytes) -> dict:
    """A request body as a JSON object of finite numbers (no NaN, Infinity or 1e400); InputError
    otherwise."""
    try:
        body = json.loads(raw or b"{}", parse_constant=_refuse_constant, parse_float=_finite_float)
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise InputError(None, "the request body is not JSON") from None
    except RecursionError:  # [[[[... within MAX_BODY: deeper than the parser goes
        raise InputError(None, "the request body nests lists or objects too deep") from None
    if not isinstance(body, dict):
        raise InputError(None, "the request body is not a JSON object")
    return body


def _query_int(query: dict, key: str) -> int:
    """A whole number of the query string (-1 when absent); InputError naming the parameter otherwise."""
    text = query.get(key, ["-1"])[0]
    try:
        return int(text)
    except ValueError:
        raise InputError(None, f"'{key}' must be a whole number, got {_shown(text)}") from None


def _host_name(host: str) -> str:
    """A bound address as a Host header spells it (IPv6 in brackets)."""
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


def allowed_hosts(bound_host: str, port: int) -> set[str]:
    """The `Host` values (host:port) a page of this server is loaded from: the bound address, and the
    loopback names when it listens on loopback or on every interface."""
    names = {_host_name(bound_host)}
    if bound_host in WILDCARD or bound_host in ("127.0.0.1", "::1", "localhost"):
        names.update(LOOPBACK)
    if bound_host in WILDCARD:
        names.update({socket.gethostname(), socket.getfqdn()})
    names = {n.lower() for n in names if n and n not in WILDCARD}
    # a browser leaves out the scheme's default port
    return {f"{n}:{port}" for n in names} | (names if port == 80 else set())


def _is_ip_literal(host: str) -> bool:
    try:
        ipaddress.ip_address(host.strip("[]"))
        return True
    except ValueError:
        return False


class _Handler(BaseHTTPRequestHandler):
    session: EditorSession
    roots: list[Path]
    token: str
    hosts: set[str]  # host:port values this server answers to
    any_ip: bool  # listening on every interface: any IP literal with our port is ours too
    port: int
    server_version = "vq-mitsuba"

    def log_message(self, format, *args):  # quiet: the terminal shows the address and errors only
        pass

    def _send(self, status: int, body: bytes, ctype: str, headers: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, v in (headers or {}).items():
            self.send_header(k, str(v))
        self.end_headers()
        try:
            self.wfile.write(body)
        except (BrokenPipeError, ConnectionResetError):  # the page went away (reload, closed tab)
            pass

    def _json(self, data, status: int = 200) -> None:
        self._send(status, json.dumps(finite_json(data), allow_nan=False).encode(), "application/json")

    def _not_found(self) -> None:
        self._send(HTTPStatus.NOT_FOUND, b"not found", "text/plain; charset=utf-8")

    def _ours(self, host: str) -> bool:
        """`host` (host:port, as a Host header or an Origin's authority gives it) names this server.
        Any other name could be an attacker's domain resolved to us (DNS rebinding)."""
        host = host.strip().lower()
        if host in self.hosts:
            return True
        name, sep, port = host.rpartition(":")
        if not sep or "]" in port:  # no port given: the scheme's default
            name, port = host, "80"
        return self.any_ip and port == str(self.port) and _is_ip_literal(name)

    def _refused(self) -> str | None:
        """Why this request does not come from our own page's address (None: it may)."""
        if not self._ours(self.headers.get("Host", "")):
            return "the Host header does not name this editor's address"
        origin = self.headers.get("Origin")
        if origin is not None:
            url = urlsplit(origin)
            if url.scheme != "http" or not self._ours(url.netloc):
                return "requests from other web pages are refused"
        return None

    def _forbid(self, why: str) -> None:
        self._json({"error": why}, HTTPStatus.FORBIDDEN)

    def do_GET(self):
        why = self._refused()
        if why:
            return self._forbid(why)
        url = urlsplit(self.path)
        path = url.path
        if path in PAGES:
            name, ctype = PAGES[path]
            body = (STATIC / name).read_bytes()
            if name == "index.html":
                body = body.replace(TOKEN_SLOT.encode(), self.token.encode())
            return self._send(200, body, ctype)
        if path == "/api/state":
            return self._json(self.session.state())
        if path == "/api/frame":
            q = parse_qs(url.query)
            try:
                version, spp = (_query_int(q, key) for key in ("version", "spp"))
            except InputError as exc:
                return self._json({"error": str(exc)}, 400)
            frame = self.session.wait_frame(version, spp)
            if frame is None:
                return self._send(204, b"", "text/plain")
            return self._send(200, frame.png, "image/png", {"X-Frame-Version": frame.version, "X-Frame-Spp": frame.spp,
                                                             "X-Frame-Seconds": f"{frame.change_s:.3f}"})
        if path.startswith("/run/"):
            file = run_file(self.roots, path[len("/run/"):])
            if file is None:
                return self._not_found()
            return self._send(200, file.read_bytes(), TYPES.get(file.suffix.lower(), "application/octet-stream"))
        return self._not_found()

    def do_POST(self):
        why = self._refused()
        if why:
            return self._forbid(why)
        if not hmac.compare_digest(self.headers.get(TOKEN_HEADER, "").encode(), self.token.encode()):
            return self._forbid(f"missing or wrong {TOKEN_HEADER}: reload the editor's page")
        ctype = self.headers.get("Content-Type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            return self._json({"error": "the request body must be application/json"},
                              HTTPStatus.UNSUPPORTED_MEDIA_TYPE)
        path = urlsplit(self.path).path
        action = path[len("/api/"):] if path.startswith("/api/") else None
        if action not in ACTIONS:
            return self._not_found()
        handler = ACTIONS[action][1]
        try:
            try:
                length = int(self.headers.get("Content-Length") or 0)
            except ValueError:
                raise InputError(None, "Content-Length is not a whole number") from None
            if length < 0:
                raise InputError(None, f"Content-Length {length} is negative")
            if length > MAX_BODY:
                raise InputError(None, "request too large")
            body = parse_body(self.rfile.read(length) if length else b"{}")
            check_fields(action, body)
            result = handler(self.session, body)
        except UserError as exc:
            return self._json({"error": str(exc)}, 400)
        except KeyError as exc:
            return self._json({"error": f"the request has no {exc}"}, 400)
        except (TypeError, ValueError, OverflowError) as exc:  # the edits' checks say what is wrong
            return self._json({"error": f"cannot do that: {exc}"}, 400)
        self._json({"ok": True, **(result or {}), "state": self.session.state()})


# --- the request bodies: every field checked, a wrong one refused with a sentence naming it --------

_REQUIRED = object()  # a field without a default


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _wrong(field: str, what: str, value) -> InputError:
    return InputError(None, f"'{field}' must be {what}, got {_shown(value)}")


def _value(body: dict, key: str, default=_REQUIRED):
    if key not in body:
        if default is _REQUIRED:
            raise InputError(None, f"the request has no '{key}'")
        return default
    return body[key]


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _finite(value) -> float | None:
    """`value` as a finite float; None when it is not a finite number (a bool or a string is not)."""
    if not _is_number(value):
        return None
    try:
        number = float(value)
    except OverflowError:  # an integer beyond any float
        return None
    return number if math.isfinite(number) else None


def _whole(value) -> int | None:
    """`value` as an int when it is a whole number (2 or 2.0), else None."""
    number = _finite(value)
    return int(number) if number is not None and number.is_integer() else None


def _text(body: dict, key: str, default=_REQUIRED) -> str:
    value = _value(body, key, default)
    if not isinstance(value, str):
        raise _wrong(key, "a string", value)
    return value


def _number(body: dict, key: str, default: float, low: float | None = None, high: float | None = None) -> float:
    """A finite number of the request (within low..high when given); InputError naming the field otherwise."""
    value = _value(body, key, default)
    number = _finite(value)
    if number is None:
        raise _wrong(key, "a finite number", value)
    if low is not None and not low <= number <= high:
        raise _wrong(key, f"a number from {low:g} to {high:g}", value)
    return number


def _flag(body: dict, key: str) -> bool:
    value = _value(body, key, False)
    if not isinstance(value, bool):
        raise _wrong(key, "true or false", value)
    return value


def _materials(s: EditorSession, body: dict) -> list[int] | None:
    value = _value(body, "materials", None)
    if value is None:
        return None
    ids = [_whole(k) for k in value] if isinstance(value, list) else None
    if ids is None or None in ids:
        which = f"1..{s.num_materials}" if s.num_materials else "none: this run has no discrete branch"
        raise _wrong("materials", f"a list of material numbers (whole numbers; this run's: {which})", value)
    return ids


def _pixel(body: dict) -> tuple[int, int] | None:
    value = _value(body, "pixel", None)
    if value is None:
        return None
    xy = [_whole(v) for v in value] if isinstance(value, list) else []
    if len(xy) != 2 or None in xy:
        raise _wrong("pixel", "two whole numbers [x, y] (a pixel of the view)", value)
    return xy[0], xy[1]


def _box(body: dict) -> list[list[float]] | None:
    value = _value(body, "box", None)
    if value is None:
        return None
    corners = [[_finite(v) for v in c] if isinstance(c, list) else [] for c in value] if isinstance(value, list) else []
    if len(corners) != 2 or any(len(c) != 3 or None in c for c in corners):
        raise _wrong("box", "two corners of three finite numbers, [[x0, y0, z0], [x1, y1, z1]]", value)
    return corners


CHANGE_FIELDS = ("op", "key", "value")


def _changes(body: dict) -> list[dict] | None:
    """The list of changes, each an object with 'key' and 'value' (and 'op'); their values are checked
    by the edit (`EditorSession.edit`), which names the key."""
    from vq_mitsuba.models.material_edits import KEYS, OPS

    value = _value(body, "changes", None)
    if value is None:
        return None
    if not isinstance(value, list):
        raise _wrong("changes", 'a list of changes, each {"key": ..., "value": ...}', value)
    for i, change in enumerate(value):
        field = f"changes[{i}]"
        if not isinstance(change, dict):
            raise _wrong(field, 'a change, an object {"key": ..., "value": ...}', change)
        unknown = [k for k in change if k not in CHANGE_FIELDS]
        if unknown:
            raise InputError(None, f"'{field}' has an unknown field '{unknown[0]}' (a change has "
                                   f"{', '.join(CHANGE_FIELDS)})")
        for key in ("key", "value"):
            if key not in change:
                raise InputError(None, f"'{field}' is a change without '{key}': give 'key' and 'value'")
        if not isinstance(change["key"], str):
            raise _wrong(f"{field}.key", f"one of {', '.join(KEYS)}", change["key"])
        if "op" in change and not isinstance(change["op"], str):
            raise _wrong(f"{field}.op", f"one of {', '.join(OPS)}", change["op"])
    return value


def _texture_size(body: dict) -> int:
    from vq_mitsuba.export.formats import check_texture_size

    return check_texture_size(_value(body, "texture_size", 1024), "'texture_size'")


def _select(s: EditorSession, b: dict) -> dict:
    sel = s.select(materials=_materials(s, b), box=_box(b), pixel=_pixel(b), add=_flag(b, "add"))
    return {"selection": sel.to_dict()}


def _edit(s: EditorSession, b: dict) -> dict:
    preset = _value(b, "preset", None)
    if preset is not None and not isinstance(preset, str):
        raise _wrong("preset", "the name of a library material (a string)", preset)
    return {"label": s.edit(_changes(b), preset, _flag(b, "live")).label}


def _save(s: EditorSession, b: dict) -> dict:
    return {"path": str(s.save(_text(b, "name")).dir)}


# action -> (the fields its body may hold, what it does with them)
ACTIONS = {
    "view": (("name",), lambda s, b: s.set_view(_text(b, "name"))),
    "orbit": (("yaw", "pitch", "zoom"),
              lambda s, b: s.orbit_view(_number(b, "yaw", 0), _number(b, "pitch", 0), _number(b, "zoom", 1, 0.2, 5))),
    "mode": (("mode",), lambda s, b: s.set_mode(_text(b, "mode"))),
    "lighting": (("envmap", "rotate", "exposure"),
                 lambda s, b: s.set_lighting(_text(b, "envmap", "fitted"), _number(b, "rotate", 0),
                                             _number(b, "exposure", 0, -64, 64))),
    "select": (("materials", "box", "pixel", "add"), _select),
    "edit": (("changes", "preset", "live"), _edit),
    "undo": ((), lambda s, b: s.undo()),
    "redo": ((), lambda s, b: s.redo()),
    "save": (("name",), _save),
    "export": (("name", "format", "texture_size"),
               lambda s, b: s.export(_text(b, "name"), _text(b, "format"), _texture_size(b))),
}


def check_fields(action: str, body: dict) -> None:
    """Refuse a field the action does not take, naming the ones it does."""
    fields = ACTIONS[action][0]
    unknown = [k for k in body if k not in fields]
    if unknown:
        takes = f"takes {', '.join(fields)}" if fields else "takes no fields"
        raise InputError(None, f"unknown field '{unknown[0]}' (/api/{action} {takes})")


def make_server(session: EditorSession, host: str = DEFAULT_HOST, port: int = 8080) -> ThreadingHTTPServer:
    """An HTTP server for `session` bound to host:port (port 0: any free port). Its `token` is the
    per-server secret every POST must carry (the served page holds it)."""
    roots = [session.run.dir]
    if session.run.is_edit():
        roots.append(session.run.source().dir)
    handler = type("Handler", (_Handler,), {"session": session, "roots": roots})
    try:
        server = ThreadingHTTPServer((host, int(port)), handler)
    except OSError as exc:
        raise InputError(None, _listen_error(host, int(port), exc)) from None
    server.daemon_threads = True
    bound_port = server.server_address[1]
    handler.token = server.token = secrets.token_urlsafe(32)
    handler.hosts = allowed_hosts(host, bound_port) | allowed_hosts(str(server.server_address[0]), bound_port)
    handler.any_ip = host in WILDCARD
    handler.port = bound_port
    return server


def _listen_error(host: str, port: int, exc: OSError) -> str:
    """Why the editor cannot listen on host:port, and which option to change."""
    if isinstance(exc, socket.gaierror):
        return f"--host {host}: no such host name or address ({exc.strerror or exc})"
    if exc.errno == errno.EADDRNOTAVAIL:
        return f"--host {host}: not an address of this machine; choose one it has (e.g. 127.0.0.1)"
    if exc.errno == errno.EADDRINUSE:
        return f"port {port} is in use on {host}; choose another --port"
    if exc.errno == errno.EACCES:
        return f"port {port} needs privileges this process lacks; choose another --port (above 1023)"
    return f"cannot listen on {host}:{port} ({exc.strerror or exc}); check --host and --port"


def _loopback(host: str) -> bool:
    """Whether only this machine can reach `host` (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def serve(run_dir: str | Path, host: str = DEFAULT_HOST, port: int = 8080, envmap_dir: str | Path | None = None,
          size: int = 256) -> None:
    """Run the editor until Ctrl-C."""
    if threading.current_thread() is threading.main_thread():
        # A process started in the background of a non-interactive shell inherits SIGINT ignored.
        signal.signal(signal.SIGINT, signal.default_int_handler)
    session = EditorSession(run_dir, envmap_dir=envmap_dir, size=size)
    server = make_server(session, host, port)
    session.start()
    bound_host, bound_port = server.server_address[:2]
    # Printed, not notes: the editor's address and state are this command's output, shown even when quiet.
    print(f"vq-mitsuba editor for {session.run.dir} at http://{bound_host}:{bound_port}/  (Ctrl-C stops)", flush=True)
    if not _loopback(bound_host):
        print(f"listening on {bound_host}: anyone who can reach this machine can open the editor", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        print("stopping the editor", flush=True)
    finally:
        server.server_close()
        session.stop()
