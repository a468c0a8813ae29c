"""The local web surface is safe to leave running (issue 45): the status server and the WebSocket server (with the
viewer on its port) serve only requests that name this machine (DNS rebinding: ``Host: evil.example``), pages of
their own origin or a configured one (another site's page, a ``file://`` page: ``Origin: null``), and change state
only for a request a web page cannot send (``X-Mocapd-Request``).

Raw HTTP requests on loopback (what curl sends), the websockets client, and real headless Chromium loading an
attacker's page from another loopback port, from ``evil.example`` resolved to 127.0.0.1 (the rebinding shape) and
from ``file://``: each attack is carried out by the browser and refused by the servers (nothing reaches the
daemon's side: the recorded actions stay empty), while the viewer on its own origin still connects and resets."""

from __future__ import annotations

import asyncio
import contextlib
import http.server
import json
import socket
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus
from websockets.typing import Origin

from mocapd.core.rate_limit import TokenBucket
from mocapd.core.skeleton import Skeleton
from mocapd.io.ws_server import ServerSettings, WebSocketStreamServer
from mocapd.protocols.web_access import WebAccess
from mocapd.protocols.ws_stream import StreamDescription
from mocapd.service.http_status import StatusServer
from tests.cdp import Page, chromium_page

SKEL = Skeleton.from_height(1.75)
EVIL = "evil.example"


class Servers:
    """A status server with a heading-reset action and a WebSocket server (the viewer on its port) with the
    reset command, both recording who reached the daemon's side."""

    def __init__(self, allowed_origins: tuple[str, ...] = ()) -> None:
        self.resets: list[str] = []  # who asked, for every request that got through
        self.http = StatusServer(
            lambda: {"ready": True, "devices": ["/dev/ttyUSB0 serial 00B421E6"]}, lambda _doc: b"mocapd_up 1\n",
            actions={"/heading/reset": self._reset}, allowed_origins=allowed_origins,
        )  # fmt: skip
        self.ws = WebSocketStreamServer(
            ServerSettings(port=0, status_hz=0, allowed_origins=allowed_origins),
            StreamDescription(60.0, {"default": SKEL}),
            commands={"reset_heading": lambda _args, who: self._reset({}, who)},
        )

    def _reset(self, _query: dict[str, str], who: str) -> dict[str, Any]:
        self.resets.append(who)
        return {"t_ns": 0, "source": who, "suits": {}}

    async def __aenter__(self) -> Servers:
        await self.http.start()
        await self.ws.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.ws.aclose()
        await self.http.close()


async def raw(port: int, request: str) -> tuple[int, dict[str, str], bytes]:
    """Send one request as written (what curl would send), read the whole answer."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(request.encode())
    await writer.drain()
    async with asyncio.timeout(10):
        data = b""
        while chunk := await reader.read(65536):
            data += chunk
            head, sep, body = data.partition(b"\r\n\r\n")
            if sep and b"Content-Length" in head:
                n = int(next(h for h in head.split(b"\r\n") if h.startswith(b"Content-Length")).split(b":")[1])
                if len(body) >= n:
                    break
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.lower(): v for k, _, v in (line.partition(": ") for line in lines[1:])}
    return int(lines[0].split(" ")[1]), headers, body


def post(port: int, headers: str, body: str = "", target: str = "/heading/reset") -> str:
    return (f"POST {target} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{headers}Content-Length: {len(body)}\r\n\r\n"
            + body)  # fmt: skip


# ------------------------------------------------------------------------------------------- the rules
def test_host_and_origin_rules() -> None:
    local = WebAccess("127.0.0.1")
    for host in ("127.0.0.1:8766", "localhost:8766", "LOCALHOST", "[::1]:8766", "127.0.0.1", "localhost:9000"):
        assert local.host_ok(host), host
    for host in (f"{EVIL}:8766", EVIL, "10.0.0.1:8766", "127.0.0.1.evil.example", "localhost.evil.example", "",
                 "[::1", "localhost:0", "localhost:99999", "127.0.0.1:8766:1"):  # fmt: skip
        assert not local.host_ok(host), host
    assert local.host_ok(None)  # no Host header: not a browser
    # Origin: none (not a browser), the page's own origin (also through a tunnel), a configured one; never null.
    assert local.origin_ok(None, "127.0.0.1:8766")
    assert local.origin_ok("http://127.0.0.1:8766", "127.0.0.1:8766")
    assert local.origin_ok("http://localhost:9000", "localhost:9000")
    assert local.origin_ok("http://[::1]:8766", "[::1]:8766")
    assert not local.origin_ok("null", "127.0.0.1:8766")
    assert not local.origin_ok(f"http://{EVIL}:8766", "127.0.0.1:8766")
    assert not local.origin_ok(f"http://{EVIL}:8766", f"{EVIL}:8766")  # rebinding: same origin, foreign Host
    assert not local.origin_ok("http://localhost:3000", "localhost:8766")  # another local site
    assert not local.origin_ok("http://127.0.0.1:8766/x", "127.0.0.1:8766")
    assert local.refusal(["127.0.0.1", "127.0.0.1"], []) == "host"  # two Host headers
    configured = WebAccess("0.0.0.0", ("studio.local",), ("http://localhost:3000",))
    assert configured.host_ok("192.168.1.5:8766") and configured.host_ok("Studio.Local:8766")
    assert not configured.host_ok(f"{EVIL}:8766")
    assert configured.origin_ok("http://LOCALHOST:3000", "127.0.0.1:8766")
    assert configured.origin_ok("http://studio.local:8766", "studio.local:8766")


def test_the_reset_bucket_allows_a_burst_then_its_rate() -> None:
    s = 1_000_000_000
    b = TokenBucket(rate_per_s=1.0, burst=3, now_ns=0)
    assert [b.take(0) for _ in range(3)] == [0.0, 0.0, 0.0]
    assert b.take(0) == pytest.approx(1.0) and b.take(s // 2) == pytest.approx(0.5)
    assert b.take(s) == 0.0 and b.take(s) > 0
    assert b.take(100 * s) == 0.0 and b.allowed == 5 and b.refused == 3  # a quiet spell refills only the burst
    assert [b.take(100 * s) for _ in range(3)][-1] > 0


# ------------------------------------------------------------------------------------------- curl
@pytest.mark.asyncio
async def test_the_status_server_refuses_foreign_hosts_origins_and_simple_posts() -> None:
    async with Servers() as s:
        port = s.http.port
        ok = f"GET /status HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n"
        assert (await raw(port, ok))[0] == 200
        # DNS rebinding: the name is the attacker's, the address ours. Device paths and serials stay in.
        code, _, body = await raw(port, f"GET /status HTTP/1.1\r\nHost: {EVIL}:{port}\r\n\r\n")
        assert code == 421 and b"ttyUSB0" not in body
        for origin in (f"http://{EVIL}:{port}", "null", "http://localhost:3000"):
            code, _, body = await raw(
                port, f"GET /status HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nOrigin: {origin}\r\n\r\n"
            )
            assert code == 403 and b"ttyUSB0" not in body, origin
        # The simple requests a page may send anywhere without asking: text/plain, a form, no body.
        for extra, body_ in (("Content-Type: text/plain\r\n", "reset"),
                               ("Content-Type: application/x-www-form-urlencoded\r\n", "suit=walker"),
                               ("Content-Type: multipart/form-data; boundary=x\r\n", "--x--"), ("", "")):  # fmt: skip
            assert (await raw(port, post(port, extra, body_)))[0] == 403, extra
            assert (await raw(port, post(port, extra + f"Origin: http://{EVIL}\r\n", body_)))[0] == 403
        assert (await raw(port, post(port, "X-Mocapd-Request: \r\n")))[0] == 403  # empty
        # With the header but from another site's page (a preflight would have been needed and was refused).
        assert (await raw(port, post(port, f"X-Mocapd-Request: 1\r\nOrigin: http://{EVIL}:{port}\r\n")))[0] == 403
        rebound = f"POST /heading/reset HTTP/1.1\r\nHost: {EVIL}:{port}\r\nX-Mocapd-Request: 1\r\n\r\n"
        assert (await raw(port, rebound))[0] == 421
        # The preflight itself: refused, and no Access-Control-* header grants anything.
        code, headers, _ = await raw(port, f"OPTIONS /heading/reset HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nOrigin: "
                                           f"http://{EVIL}\r\nAccess-Control-Request-Method: POST\r\n\r\n")  # fmt: skip
        assert code in (403, 405) and not any(k.startswith("access-control") for k in headers)
        assert s.resets == []
        assert s.http.refused.as_dict() == {"host": 2, "origin": 9, "csrf": 5}
        # What mocapd reset-heading sends: carried out, the client named in the log.
        code, _, body = await raw(port, post(port, "X-Mocapd-Request: mocapd reset-heading\r\n"))
        assert code == 200 and json.loads(body)["source"].startswith("HTTP request from 127.0.0.1:")
        assert s.resets[0].endswith("(mocapd reset-heading)")


@pytest.mark.asyncio
async def test_the_status_server_answers_an_action_over_its_rate_limit_with_429() -> None:
    from mocapd.errors import RateLimitError

    bucket = TokenBucket(1.0, 2, 0)

    def reset(_q: dict[str, str], _who: str) -> dict[str, Any]:
        wait = bucket.take(0)
        if wait:
            raise RateLimitError("too many", wait)
        return {}

    server = StatusServer(lambda: {}, lambda _d: b"", actions={"/heading/reset": reset})
    port = await server.start()
    try:
        codes = [(await raw(port, post(port, "X-Mocapd-Request: 1\r\n")))[:2] for _ in range(4)]
    finally:
        await server.close()
    assert [c for c, _ in codes] == [200, 200, 429, 429] and codes[2][1]["retry-after"] == "1"
    assert server.refused.as_dict() == {"rate": 2}


@pytest.mark.asyncio
async def test_the_websocket_refuses_foreign_hosts_and_origins_and_serves_its_own() -> None:
    async with Servers(allowed_origins=("http://localhost:3000",)) as s:
        port = s.ws.port
        url = f"ws://127.0.0.1:{port}/"
        refused: list[int] = []
        for kwargs in ({"origin": "null"}, {"origin": f"http://{EVIL}:{port}"}, {"origin": "http://localhost:4000"},
                       {"host": "127.0.0.1", "port": port, "uri": f"ws://{EVIL}:{port}/"}):  # fmt: skip
            uri = str(kwargs.pop("uri", url))
            with pytest.raises(InvalidStatus) as info:
                async with connect(uri, open_timeout=5, **kwargs):
                    pass
            refused.append(info.value.response.status_code)
        assert refused == [403, 403, 403, 421]
        # The viewer page under a foreign name (rebinding) is not served either.
        code, _, body = await raw(port, f"GET / HTTP/1.1\r\nHost: {EVIL}:{port}\r\n\r\n")
        assert code == 421 and b"<html" not in body.lower()
        assert s.ws.refused["origin"] == 3 and s.ws.refused["host"] == 2
        # No Origin (Python, Unity, Node), the viewer's own origin, a configured one: served.
        own = [(url, None), (url, f"http://127.0.0.1:{port}"), (f"ws://localhost:{port}/", f"http://localhost:{port}"),
               (url, "http://localhost:3000")]  # fmt: skip
        for where, origin in own:
            async with connect(where, origin=Origin(origin) if origin else None, open_timeout=5) as c:
                await c.send(json.dumps({"type": "reset_heading"}))
                async with asyncio.timeout(5):
                    while "heading_reset" not in str(await c.recv()):
                        pass
        assert len(s.resets) == 4 and s.resets[-1].endswith("page 'http://localhost:3000'"), s.resets


# ------------------------------------------------------------------------------------------- Chromium
ATTACK = """<!doctype html><html><body><script>
// Everything a page of another site can try against the daemon: simple POSTs (no preflight), a form, a POST with
// the custom header (needs a preflight), reading /status, and the WebSocket (poses, camera images, a reset).
window.results = {};
(async () => {
  const r = window.results, http = "HTTP_BASE", ws = "WS_URL";
  const sent = async (what, init) => {
    try {
      const resp = await fetch(http + "/heading/reset", init);
      return init.mode === "no-cors" ? "sent" : resp.status;
    } catch (e) { return "blocked"; }
  };
  r.textPlain = await sent("text", {method: "POST", mode: "no-cors", headers: {"Content-Type": "text/plain"},
                                    body: "reset"});
  r.urlencoded = await sent("form", {method: "POST", mode: "no-cors", body: new URLSearchParams({suit: "walker"})});
  r.custom = await sent("custom", {method: "POST", headers: {"X-Mocapd-Request": "1"}});
  try { r.status = await (await fetch(http + "/status")).text(); } catch (e) { r.status = "blocked"; }
  r.form = await new Promise((resolve) => {
    const frame = document.createElement("iframe"), form = document.createElement("form");
    frame.name = "sink"; document.body.appendChild(frame);
    form.method = "POST"; form.action = http + "/heading/reset"; form.target = "sink";
    form.innerHTML = '<input name="suit" value="walker">'; document.body.appendChild(form);
    frame.onload = () => resolve("submitted"); form.submit(); setTimeout(() => resolve("timeout"), 5000);
  });
  r.ws = await new Promise((resolve) => {
    const got = {opened: false, messages: 0, cameras: 0};
    const s = new WebSocket(ws);
    s.onopen = () => {
      got.opened = true;
      s.send(JSON.stringify({type: "subscribe", encoding: "json", cameras: true}));
      s.send(JSON.stringify({type: "reset_heading"}));
    };
    s.onmessage = (e) => { got.messages++; if (String(e.data).includes('"camera"')) got.cameras++; };
    s.onclose = () => resolve(got);
    setTimeout(() => { s.close(); resolve(got); }, 3000);
  });
  r.done = true;
})();
</script></body></html>"""


@contextlib.contextmanager
def attacker_site(page: Callable[[], str]) -> Iterator[int]:
    """Another web site on loopback (its own port): serves ``page()`` at /attack.html."""

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = page().encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield int(server.server_address[1])
    finally:
        server.shutdown()
        server.server_close()


def attack_page(http_base: str, ws_url: str) -> str:
    return ATTACK.replace("HTTP_BASE", http_base).replace("WS_URL", ws_url)


async def run_attack(page: Page, url: str) -> dict[str, Any]:
    await page.call("Page.navigate", url=url)
    await page.wait_for("window.results && window.results.done === true", 30, f"the attack of {url}")
    results: dict[str, Any] = await page.evaluate("window.results")
    return results


def assert_refused(results: dict[str, Any], what: str) -> None:
    """The browser did its part (the simple requests went out); the servers let nothing through."""
    assert results["textPlain"] == "sent" and results["urlencoded"] == "sent", (what, results)
    assert results["custom"] == "blocked", (what, results)  # the preflight was refused
    assert results["status"] == "blocked", (what, results)  # not readable from another origin
    assert results["form"] == "submitted", (what, results)
    assert results["ws"] == {"opened": False, "messages": 0, "cameras": 0}, (what, results)


@pytest.mark.asyncio
async def test_pages_of_other_sites_and_file_pages_can_neither_drive_nor_watch_the_daemon() -> None:
    rebinding = f"--host-resolver-rules=MAP {EVIL} 127.0.0.1"
    async with contextlib.AsyncExitStack() as stack:
        s = await stack.enter_async_context(Servers())
        hp, wp = s.http.port, s.ws.port
        # Another site on this machine (another loopback port), targeting the daemon's addresses.
        local = attack_page(f"http://127.0.0.1:{hp}", f"ws://127.0.0.1:{wp}/")
        other = stack.enter_context(attacker_site(lambda: local))
        page = await stack.enter_async_context(chromium_page("about:blank", flags=[rebinding]))
        assert_refused(await run_attack(page, f"http://127.0.0.1:{other}/attack.html"), "another local site")
        # The rebinding shape: the attacker's name resolves to 127.0.0.1, its page targets that name.
        rebound = attack_page(f"http://{EVIL}:{hp}", f"ws://{EVIL}:{wp}/")
        evil = stack.enter_context(attacker_site(lambda: rebound))
        assert_refused(await run_attack(page, f"http://{EVIL}:{evil}/attack.html"), "a rebound name")
        # A page saved to disk and opened (Origin: null).
        folder = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        (folder / "attack.html").write_text(local)
        assert_refused(await run_attack(page, (folder / "attack.html").as_uri()), "a file:// page")
        # Under the rebound name the viewer and /status themselves are not served (the page's own origin would be
        # evil.example: everything it loads would be readable by the attacker's script).
        for url in (f"http://{EVIL}:{wp}/", f"http://{EVIL}:{hp}/status"):
            await page.call("Page.navigate", url=url)
            await page.wait_for("document.readyState == 'complete' && document.body !== null", 20, url)
            text = await page.evaluate("document.body.innerText")
            assert "answers only to its own names" in text and "ttyUSB0" not in text, (url, text)
            assert await page.evaluate("typeof window.mocapdViewer") == "undefined"
        assert s.resets == []  # nothing reached the daemon
        assert s.ws.refused["origin"] == 2 and s.ws.refused["host"] >= 2, s.ws.refused  # (and the favicon)
        # 2 pages x 5 requests (two no-cors POSTs, the preflight, /status, the form) with a foreign Origin; those of
        # the rebound name and the two navigations with a foreign Host (Chromium retries a 421 once, favicons)
        refused = s.http.refused.as_dict()
        assert refused["origin"] >= 10 and refused["host"] >= 6 and "csrf" not in refused, refused

        # The viewer on its own origin: connects, and its heading-reset button reaches the daemon.
        for host in ("127.0.0.1", "localhost"):
            await page.call("Page.navigate", url=f"http://{host}:{wp}/")
            await page.wait_for("window.mocapdViewer && mocapdViewer.state.hellos > 0", 30, "the viewer's hello")
            await page.evaluate("mocapdViewer.resetHeading()")
            await page.wait_for("mocapdViewer.state.headingResets == 1", 10, "the heading reset's answer")
        assert len(s.resets) == 2 and s.resets[1].endswith(f"page 'http://localhost:{wp}'"), s.resets


@pytest.mark.asyncio
async def test_a_configured_origin_may_use_the_websocket_from_chromium() -> None:
    page_text = [""]  # the site's port is needed first: its origin is configured before the servers start
    async with contextlib.AsyncExitStack() as stack:
        port = stack.enter_context(attacker_site(lambda: page_text[0]))
        s = await stack.enter_async_context(Servers(allowed_origins=(f"http://127.0.0.1:{port}",)))
        page_text[0] = attack_page(f"http://127.0.0.1:{s.http.port}", f"ws://127.0.0.1:{s.ws.port}/")
        page = await stack.enter_async_context(chromium_page("about:blank"))
        results = await run_attack(page, f"http://127.0.0.1:{port}/attack.html")
    assert results["ws"]["opened"] and results["ws"]["messages"] >= 2, results  # hello, and the reset's answer
    # Only the WebSocket: the status server's actions stay out of reach of any page (no CORS is granted).
    assert results["custom"] == "blocked" and results["status"] == "blocked"
    assert len(s.resets) == 1 and s.resets[0].startswith("WebSocket client"), s.resets


@pytest.mark.asyncio
async def test_the_web_section_reaches_the_servers() -> None:
    """``[web] allowed_hosts`` and ``allowed_origins`` of a config file admit that name and that page's origin on
    the daemon's WebSocket (as the daemon builds it) and nothing else."""
    from mocapd.service.config import parse_config
    from mocapd.service.outputs.websocket import websocket_sinks

    web = {"allowed_hosts": ["studio.local"], "allowed_origins": ["http://localhost:3000"]}
    cfg = parse_config({"websocket": {"port": 0, "status_hz": 0.0}, "web": web})
    (server,) = websocket_sinks(cfg, SKEL)
    await server.start()
    try:
        port = server.port
        for uri, origin in ((f"ws://studio.local:{port}/", f"http://studio.local:{port}"),
                            (f"ws://127.0.0.1:{port}/", "http://localhost:3000")):  # fmt: skip
            async with connect(uri, host="127.0.0.1", port=port, origin=Origin(origin), open_timeout=5) as c:
                assert "hello" in str(await asyncio.wait_for(c.recv(), 5))
        refused: list[tuple[str, Origin | None]] = [
            (f"ws://studio.example:{port}/", None),  # a name not configured, no Origin: refused for its Host
            (f"ws://127.0.0.1:{port}/", Origin("http://localhost:3001")),
        ]
        for uri, other in refused:
            with pytest.raises(InvalidStatus):
                async with connect(uri, host="127.0.0.1", port=port, origin=other):
                    pass
    finally:
        await server.aclose()
    assert server.refused["host"] == 1 and server.refused["origin"] == 1


@pytest.mark.asyncio
async def test_the_status_server_on_an_inherited_socket_is_built_as_the_daemons_own() -> None:
    """The camera demo's daemon serves ``/status`` on a listening socket its parent bound in the host's network
    namespace (``RunOptions.sockets``). That server is built as the daemon's own: ``[web]`` reaches it (its
    configured name and page origin are served), foreign names and origins are refused, a POST needs the header.
    Before, it was built without ``[web]``: the configured name was refused with 421."""
    from mocapd.service.assembly import RunOptions, Sockets, assembled
    from mocapd.service.config import parse_config

    web = {"allowed_hosts": ["studio.local"], "allowed_origins": ["http://localhost:3000"]}
    cfg = parse_config({"imu": {"slimevr": {"enabled": True, "port": 0}}, "daemon": {"http_port": 0},
                        "websocket": {"enabled": False}, "web": web})  # fmt: skip
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    with assembled(cfg, RunOptions(sockets=Sockets(http=listener))) as built:
        server = built.daemon.http
        assert await server.start() == port  # it serves on the inherited socket, not on a port of its own

        async def get(host: str, origin: str | None = None) -> int:
            extra = f"Origin: {origin}\r\n" if origin else ""
            return (await raw(port, f"GET /nothing HTTP/1.1\r\nHost: {host}\r\n{extra}\r\n"))[0]

        try:
            # Served (404: past the Host and Origin checks, to the path): its own names, the configured ones.
            assert await get(f"127.0.0.1:{port}") == 404
            assert await get(f"localhost:{port}", f"http://localhost:{port}") == 404
            assert await get(f"studio.local:{port}") == 404
            assert await get(f"127.0.0.1:{port}", "http://localhost:3000") == 404
            # Refused: a foreign name (DNS rebinding), foreign pages, a simple POST.
            assert await get(f"{EVIL}:{port}") == 421
            assert await get(f"127.0.0.1:{port}", f"http://{EVIL}:{port}") == 403
            assert await get(f"127.0.0.1:{port}", "http://localhost:3001") == 403
            assert (await raw(port, post(port, "Content-Type: text/plain\r\n", "reset")))[0] == 403
        finally:
            await server.close()
    assert server.refused.as_dict() == {"host": 1, "origin": 2, "csrf": 1}
