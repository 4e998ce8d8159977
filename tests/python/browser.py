"""Drive headless Chromium over the DevTools Protocol (used by the dashboard tests).

usage: browser.py --url URL --screenshot OUT.png [--live-marker NAME]

Loads URL in a fresh headless Chromium, waits for the load event (and, with
--live-marker NAME, until document.body.dataset[NAME] === "open"), writes a full-page
PNG to OUT.png and prints one JSON line:
    {"event": "loaded", "dom": ..., "requests": [url, ...], "errors": [str, ...]}
Then reads JSON lines from stdin, each {"wait_text": {"id": ID, "text": TEXT}}: polls
until document.getElementById(ID).textContent.trim() === TEXT (30 s at most) and prints
    {"event": "updated", "ok": bool, "text": last_seen, "dom": ..., "requests": ..., "errors": ...}
On EOF of stdin it closes the browser and exits 0. On any failure it prints
{"event": "error", "message": ...} and exits 1. Every wait has a timeout.

Needs the Debian `chromium` package and the `websocket-client` pip package.
"""

import argparse
import base64
import ctypes
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time

import websocket

CHROMIUM = os.environ.get("CHROMIUM", "chromium")
FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-port=0",
    "--window-size=1400,1000", "--no-first-run", "--no-default-browser-check",
    "--disable-background-networking", "--disable-component-update",
    "--disable-default-apps", "--disable-sync", "--metrics-recording-only",
    "--disable-extensions", "--disable-domain-reliability", "--disable-breakpad",
    "--disable-client-side-phishing-detection", "--no-pings",
    "--password-store=basic", "--use-mock-keychain",
    "--disable-features=NetworkTimeServiceQuerying,Translate,OptimizationHints,MediaRouter",
    # Even with the flags above Chromium looks up clients2.google.com (network time),
    # update.googleapis.com and accounts.google.com by itself: resolve no host name
    # but localhost, so that nothing leaves the machine (IP literals still work).
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE localhost, EXCLUDE 127.0.0.1",
]
PORT_TIMEOUT = 30.0  # for DevToolsActivePort to appear
COMMAND_TIMEOUT = 30.0  # for any one CDP command's reply
LOAD_TIMEOUT = 30.0  # for Page.loadEventFired
LIVE_TIMEOUT = 20.0  # for the page's live marker
TEXT_TIMEOUT = 30.0  # for one wait_text
STDIN_TIMEOUT = 600.0  # for the next stdin line
MAX_SHOT_HEIGHT = 16000  # px; keeps a runaway page from making a huge PNG


class Failure(Exception):
    """A failure reported as {"event": "error"}."""


def emit(obj):
    """Print one JSON line and flush it."""
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


# --- launching Chromium ------------------------------------------------------------


def die_with_parent():
    """In the child: get SIGKILL if this script dies (Linux only, best effort)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def launch(profile, log):
    """Start Chromium on about:blank with its own process group."""
    cmd = [CHROMIUM, *FLAGS, f"--user-data-dir={profile}", "about:blank"]
    return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=log, stderr=log,
                            start_new_session=True, preexec_fn=die_with_parent)


def devtools_url(profile, proc):
    """Read ws://127.0.0.1:PORT/PATH from DevToolsActivePort, polling up to 30 s."""
    path = os.path.join(profile, "DevToolsActivePort")
    deadline = time.monotonic() + PORT_TIMEOUT
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise Failure(f"chromium exited with {proc.returncode} before DevTools was up;"
                          f" its log ends: {log_tail(profile)}")
        try:
            with open(path) as f:
                lines = f.read().split("\n")
            if len(lines) >= 2 and lines[0].strip() and lines[1].strip():
                return f"ws://127.0.0.1:{lines[0].strip()}{lines[1].strip()}"
        except FileNotFoundError:
            pass
        time.sleep(0.1)
    raise Failure("no DevToolsActivePort after 30 s")


def log_tail(profile):
    """The last lines of Chromium's own output, for error messages."""
    try:
        with open(os.path.join(profile, "chromium.log"), errors="replace") as f:
            return " | ".join(f.read().strip().splitlines()[-5:])
    except OSError:
        return "(no log)"


def shutdown(proc, cdp):
    """Browser.close, then kill the process group if still alive after 5 s."""
    if cdp is not None:
        try:
            cdp.send("Browser.close", timeout=5)
        except Exception:  # the browser may close the socket before replying
            pass
        cdp.close()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)  # also the renderers and zygote
    except ProcessLookupError:
        pass
    proc.wait()


# --- the DevTools connection -------------------------------------------------------


class Cdp:
    """One browser-level websocket; page commands go through a flat session."""

    def __init__(self, url):
        self.ws = websocket.create_connection(url, timeout=COMMAND_TIMEOUT,
                                              suppress_origin=True)
        self.next_id = 0
        self.session = None
        self.requests = []  # every request URL, in order, blocked ones too
        self.urls = {}  # requestId -> URL
        self.errors = []
        self.loaded = False

    def close(self):
        try:
            self.ws.close()
        except Exception:
            pass

    def send(self, method, params=None, session=True, timeout=COMMAND_TIMEOUT):
        """Send a command and return its result, handling events until it comes."""
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session and self.session:
            msg["sessionId"] = self.session
        self.ws.send(json.dumps(msg))
        deadline = time.monotonic() + timeout
        while True:
            reply = self.receive(deadline, method)
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise Failure(f"{method}: {reply['error'].get('message')}")
                return reply.get("result", {})

    def receive(self, deadline, what):
        """Read one message before the deadline; events are recorded on the way."""
        left = deadline - time.monotonic()
        if left <= 0:
            raise Failure(f"timed out waiting for {what}")
        self.ws.settimeout(left)
        try:
            msg = json.loads(self.ws.recv())
        except websocket.WebSocketTimeoutException:
            raise Failure(f"timed out waiting for {what}") from None
        except (websocket.WebSocketException, OSError) as e:
            raise Failure(f"DevTools connection lost waiting for {what}: {e}") from None
        if "method" in msg:
            self.on_event(msg["method"], msg.get("params", {}))
        return msg

    def pump(self, seconds):
        """Handle events for a while (used between polls)."""
        deadline = time.monotonic() + seconds
        try:
            while True:
                self.receive(deadline, "events")
        except Failure as e:
            if "timed out" not in str(e):
                raise

    def on_event(self, method, p):
        """Record requests, errors and the load event."""
        if method == "Network.requestWillBeSent":
            self.requests.append(p["request"]["url"])
            self.urls[p["requestId"]] = p["request"]["url"]
        elif method == "Page.loadEventFired":
            self.loaded = True
        elif method == "Runtime.exceptionThrown":
            self.errors.append("exception: " + exception_text(p["exceptionDetails"]))
        elif method == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
            self.errors.append("console.error: " + " ".join(arg_text(a) for a in p["args"]))
        elif method == "Log.entryAdded":
            self.on_log(p["entry"])
        elif method == "Network.loadingFailed" and p.get("blockedReason"):
            url = self.urls.get(p["requestId"], "?")
            self.errors.append(f"blocked ({p['blockedReason']}): {url}")

    def on_log(self, e):
        """Keep errors, and anything about the Content Security Policy."""
        text = e.get("text", "")
        if e.get("level") == "error" or "Content Security Policy" in text:
            where = f" ({e['url']})" if e.get("url") else ""
            self.errors.append(f"log[{e.get('source')}/{e.get('level')}]: {text}{where}")


def exception_text(d):
    """The message of a Runtime.exceptionThrown."""
    exc = d.get("exception") or {}
    return exc.get("description") or d.get("text", "?")


def arg_text(a):
    """A console argument as text."""
    if "value" in a:
        return str(a["value"])
    return a.get("description") or a.get("type", "?")


# --- the page ----------------------------------------------------------------------


def attach(cdp):
    """Open a page target and enable the domains we listen to."""
    target = cdp.send("Target.createTarget", {"url": "about:blank"}, session=False)
    att = cdp.send("Target.attachToTarget",
                   {"targetId": target["targetId"], "flatten": True}, session=False)
    cdp.session = att["sessionId"]
    for domain in ("Network", "Page", "Runtime", "Log"):
        cdp.send(f"{domain}.enable")


def evaluate(cdp, expression):
    """Evaluate a JS expression in the page and return its value."""
    r = cdp.send("Runtime.evaluate", {"expression": expression, "returnByValue": True})
    if "exceptionDetails" in r:
        raise Failure(f"evaluating {expression!r}: {exception_text(r['exceptionDetails'])}")
    return r["result"].get("value")


def navigate(cdp, url):
    """Navigate and wait for the load event."""
    cdp.loaded = False
    r = cdp.send("Page.navigate", {"url": url})
    if r.get("errorText"):
        raise Failure(f"navigating to {url}: {r['errorText']}")
    deadline = time.monotonic() + LOAD_TIMEOUT
    while not cdp.loaded:
        cdp.receive(deadline, "Page.loadEventFired")


def poll(cdp, expression, want, timeout):
    """Evaluate every 100 ms until it gives want; return (ok, last value)."""
    deadline = time.monotonic() + timeout
    while True:
        value = evaluate(cdp, expression)
        if value == want or time.monotonic() >= deadline:
            return value == want, value
        cdp.pump(0.1)


def wait_live(cdp, name):
    """Wait until document.body.dataset[name] === "open"."""
    expr = f"document.body ? document.body.dataset[{json.dumps(name)}] ?? null : null"
    ok, _ = poll(cdp, expr, "open", LIVE_TIMEOUT)
    if not ok:
        raise Failure(f'document.body.dataset.{name} never became "open" within 20 s')


def wait_text(cdp, element_id, expected):
    """Wait until the element's trimmed textContent equals expected; (ok, last text)."""
    read = (f"(() => {{ const e = document.getElementById({json.dumps(element_id)});"
            f" return e === null ? null : e.textContent.trim(); }})()")
    return poll(cdp, read, expected, TEXT_TIMEOUT)


def screenshot(cdp, out):
    """Write a full-page PNG."""
    size = cdp.send("Page.getLayoutMetrics")["cssContentSize"]
    clip = {"x": 0, "y": 0, "width": max(1, size["width"]),
            "height": max(1, min(size["height"], MAX_SHOT_HEIGHT)), "scale": 1}
    shot = cdp.send("Page.captureScreenshot",
                    {"format": "png", "captureBeyondViewport": True, "clip": clip})
    with open(out, "wb") as f:
        f.write(base64.b64decode(shot["data"]))


def snapshot(cdp, event, **extra):
    """The JSON line of an event: DOM, requests and errors so far."""
    dom = evaluate(cdp, "document.documentElement.outerHTML")
    return {"event": event, **extra, "dom": dom,
            "requests": list(cdp.requests), "errors": list(cdp.errors)}


# --- stdin -------------------------------------------------------------------------


def stdin_lines():
    """Yield stdin lines; raise Failure if none comes within STDIN_TIMEOUT."""
    fd, buf = sys.stdin.fileno(), b""
    while True:
        while b"\n" not in buf:
            ready, _, _ = select.select([fd], [], [], STDIN_TIMEOUT)
            if not ready:
                raise Failure(f"no stdin line within {STDIN_TIMEOUT:.0f} s")
            chunk = os.read(fd, 65536)
            if not chunk:
                if buf.strip():
                    yield buf.decode()
                return
            buf += chunk
        line, buf = buf.split(b"\n", 1)
        if line.strip():
            yield line.decode()


def serve_commands(cdp):
    """Answer each {"wait_text": {...}} line until EOF."""
    for line in stdin_lines():
        cmd = json.loads(line).get("wait_text")
        if not isinstance(cmd, dict) or "id" not in cmd or "text" not in cmd:
            raise Failure(f"unknown command: {line.strip()}")
        ok, text = wait_text(cdp, cmd["id"], cmd["text"])
        emit(snapshot(cdp, "updated", ok=ok, text=text))


# --- main --------------------------------------------------------------------------


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--url", required=True)
    p.add_argument("--screenshot", required=True, metavar="OUT.png")
    p.add_argument("--live-marker", metavar="NAME",
                   help='wait until document.body.dataset[NAME] === "open" (e.g. "live")')
    return p.parse_args()


def run(args, profile):
    """Everything between launching Chromium and closing it."""
    log = open(os.path.join(profile, "chromium.log"), "wb")
    proc, cdp = launch(profile, log), None
    try:
        cdp = Cdp(devtools_url(profile, proc))
        attach(cdp)
        navigate(cdp, args.url)
        if args.live_marker:
            wait_live(cdp, args.live_marker)
        screenshot(cdp, args.screenshot)
        emit(snapshot(cdp, "loaded"))
        serve_commands(cdp)
    finally:
        shutdown(proc, cdp)
        log.close()


def main():
    args = parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))  # so that finally runs
    profile = tempfile.mkdtemp(prefix="browser-py-")
    try:
        run(args, profile)
        return 0
    except (Failure, OSError, ValueError, KeyError, websocket.WebSocketException) as e:
        emit({"event": "error", "message": f"{type(e).__name__}: {e}"})
        return 1
    finally:
        shutil.rmtree(profile, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
