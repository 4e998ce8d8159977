//! The operator's console in a real browser (headless Chromium over the DevTools protocol,
//! `tests/python/browser.py`), and its HTTPS and password protection.

use std::io::{BufRead, BufReader, Write};
use std::path::Path;
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use serde_json::{Value, json};

use super::*;
use crate::suite::common::python_venv;
use crate::suite::tracker::tmp_dir;

/// Headless Chromium showing one console page, driven by `tests/python/browser.py`.
pub struct Browser {
    child: Child,
    stdin: Option<ChildStdin>,
    stdout: BufReader<ChildStdout>,
    origin: String,
    /// What the script reported once the page had loaded and gone live.
    pub loaded: Value,
}

impl Browser {
    /// Opens `http://<console><path>`, waits until its live connection is open and writes
    /// a screenshot to `shot`.
    pub fn open(console: &str, path: &str, shot: &Path) -> Self {
        assert!(
            Command::new("chromium").arg("--version").output().is_ok(),
            "the console test needs Chromium (Debian package chromium; .ci/run installs it)"
        );
        let python = python_venv(
            "browser-venv",
            "import websocket",
            &["websocket-client==1.9.2"],
        );
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/browser.py");
        let origin = format!("http://{console}");
        let mut child = Command::new(python)
            .arg(script)
            .args(["--url", &format!("{origin}{path}"), "--live-marker", "live"])
            .arg("--screenshot")
            .arg(shot)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .unwrap();
        let stdin = child.stdin.take();
        let stdout = BufReader::new(child.stdout.take().unwrap());
        let mut b = Self {
            child,
            stdin,
            stdout,
            origin,
            loaded: Value::Null,
        };
        b.loaded = b.reply("loaded");
        b
    }

    /// The script's next line, which must be the event `want`.
    fn reply(&mut self, want: &str) -> Value {
        let mut line = String::new();
        self.stdout.read_line(&mut line).unwrap();
        let v: Value =
            serde_json::from_str(&line).unwrap_or_else(|e| panic!("browser.py said {line:?}: {e}"));
        assert_eq!(v["event"], want, "browser.py: {v}");
        v
    }

    /// Waits (30 s at most) until the element `id` reads `text`; what the page then is.
    pub fn wait_text(&mut self, id: &str, text: &str) -> Value {
        let ask = json!({"wait_text": {"id": id, "text": text}});
        let stdin = self.stdin.as_mut().unwrap();
        writeln!(stdin, "{ask}").unwrap();
        stdin.flush().unwrap();
        self.reply("updated")
    }

    /// Every request the page made went to the console itself, and the browser reported
    /// no error (a script error, a policy violation, a failed load).
    pub fn assert_same_origin_and_clean(&self, report: &Value) {
        let requests = report["requests"].as_array().unwrap();
        assert!(!requests.is_empty());
        for r in requests {
            let url = r.as_str().unwrap();
            assert!(
                url.starts_with(&format!("{}/", self.origin)),
                "a request to another origin: {url}"
            );
        }
        assert_eq!(report["errors"], json!([]), "the browser reported errors");
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // End of input: the script closes the browser and exits.
        drop(self.stdin.take());
        let _ = self.child.wait();
    }
}

/// The connection rows of a structure page's DOM (`<tr class="…" id="c-…">`).
pub fn connection_rows(dom: &str) -> Vec<&str> {
    dom.split("<tr class=\"")
        .skip(1)
        .filter(|r| r.contains(" id=\"c-"))
        .collect()
}

/// The page of the loosening run as the browser shows it: every one of the 17 connection
/// rows, C1L@J1L first and in alarm, the charts and the drawing; nothing from elsewhere.
pub fn assert_browser_shows_the_alarm(b: &Browser) {
    let dom = b.loaded["dom"].as_str().unwrap();
    let rows = connection_rows(dom);
    assert_eq!(rows.len(), 17, "a row per parameter");
    assert!(
        rows[0].starts_with("alarm\" id=\"c-C1L@J1L\""),
        "{}",
        rows[0]
    );
    assert!(
        rows[0].contains("<td class=\"level\">alarm</td>"),
        "{}",
        rows[0]
    );
    for part in [
        "Filtered stiffness",
        "The structure",
        "Frequencies",
        "Misfit",
        "Cross-check",
    ] {
        assert!(dom.contains(&format!("<h2>{part}</h2>")), "no {part}");
    }
    assert!(
        dom.contains("data-live=\"open\""),
        "the live connection is open"
    );
    b.assert_same_origin_and_clean(&b.loaded);
}

/// Over HTTPS with a password file: no credentials or a wrong password get 401 with the
/// challenge, the right ones the page; the certificate verifies against its CA; plain HTTP
/// on the port gets no page.
#[test]
fn the_console_over_https_asks_for_a_password() {
    let d = tmp_dir("console-https");
    super::deploy::make_certs(&d);
    let users = d.join("users");
    let hash = bcrypt::hash("correct horse", 4).unwrap();
    std::fs::write(&users, format!("# console users\nana:{hash}\n")).unwrap();
    let tls = d.join("tls");
    let (cert, key) = (tls.join("daemon.pem"), tls.join("daemon-key.pem"));
    let env = [
        ("BOLTWATCH__CONSOLE__TLS_CERT", cert.to_str().unwrap()),
        ("BOLTWATCH__CONSOLE__TLS_KEY", key.to_str().unwrap()),
        ("BOLTWATCH__CONSOLE__USERS_FILE", users.to_str().unwrap()),
    ];
    let mut daemon = Daemon::start_env(&d, &env);
    let url = format!("https://{}/", daemon.console);
    let ca = tls.join("ca.pem");
    let curl = |user: Option<&str>| {
        let mut c = Command::new("curl");
        c.args(["-s", "--max-time", "20", "-D", "-", "--cacert"])
            .arg(&ca);
        if let Some(u) = user {
            c.args(["-u", u]);
        }
        let o = c.arg(&url).output().expect("curl");
        assert!(o.status.success(), "curl {user:?}: {o:?}");
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    wait_for(|| {
        Command::new("curl")
            .args(["-sk", &url])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    for user in [None, Some("ana:wrong"), Some("bob:correct horse")] {
        let r = curl(user);
        assert!(r.starts_with("HTTP/1.1 401"), "{user:?}: {r}");
        assert!(
            r.contains("www-authenticate: Basic realm=\"boltwatch\""),
            "{r}"
        );
        assert!(
            r.contains("content-security-policy: default-src 'none'"),
            "{r}"
        );
    }
    let ok = curl(Some("ana:correct horse"));
    assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
    assert!(
        ok.contains("<h1>Structures</h1>") && ok.contains("lab-frame"),
        "{ok}"
    );
    let plain = Command::new("curl")
        .args([
            "-s",
            "--max-time",
            "10",
            "-o",
            "/dev/null",
            "-w",
            "%{http_code}",
        ])
        .arg(format!("http://{}/", daemon.console))
        .output()
        .unwrap();
    let code = String::from_utf8_lossy(&plain.stdout);
    assert!(
        code != "200" && code != "401",
        "plain HTTP on the HTTPS port: {code}"
    );
    let exit = daemon.terminate();
    assert!(exit.success(), "{exit:?}; log:\n{}", daemon.log());
}

/// Waits (30 s at most) until `ok`.
fn wait_for(ok: impl Fn() -> bool) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    while !ok() {
        assert!(std::time::Instant::now() < deadline, "timed out");
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
}
