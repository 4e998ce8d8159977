//! Every shell example of `README.md` and `docs/` runs, as a reader would run it, so the
//! manual cannot drift from the program.
//!
//! Each page's ```` ```sh ```` blocks run in order in one fresh folder of their own (later
//! blocks use what earlier ones wrote), with `boltwatch` on the `PATH` and the repository's
//! `config/`, `recordings/`, `tests/` and `deploy/` linked in, as from the repository root;
//! `XDG_STATE_HOME` points into that folder, so a daemon's state stays there. A block must
//! exit 0. Two markers, HTML comments on the line before a fence (invisible on a rendered
//! page), say more:
//! - `<!-- example: not run, <reason> -->` before an `sh` block: it is not run, and the
//!   reason is required (a maintainer's `cargo` command, a change to the system, minutes of
//!   fitting that a slow test already covers).
//! - `<!-- example: output -->` before a `text` block: its lines, but for `...` lines, are
//!   the output the `sh` block before it prints, in order (other lines may come between).
//!
//! A block that is just `boltwatch run` starts the daemon in the background, as in a second
//! terminal; the page's next blocks (`publish`, `curl` of the metrics) talk to it, and at
//! the end of the page it is stopped with SIGINT and must exit 0. The daemon listens on its
//! default loopback ports, so pages run one after the other.
//!
//! `BOLTWATCH_EXAMPLES=<text>` runs only the pages whose path contains the text.
//!
//! Slow tier (`cargo test --features slow-tests`).

use std::io::Read;
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// The longest any one block may take (a hung example fails instead of stalling CI).
const BLOCK_TIMEOUT: Duration = Duration::from_secs(600);

/// One fenced block of a page.
struct Block {
    line: usize,
    lang: String,
    text: String,
    /// The `<!-- example: … -->` marker on the line before the fence, without its frame.
    marker: Option<String>,
}

/// The fenced blocks of a Markdown page, with indentation (a block in a list) removed.
fn blocks(page: &str) -> Vec<Block> {
    let mut out = Vec::new();
    let mut lines = page.lines().enumerate();
    let mut previous = "";
    while let Some((i, line)) = lines.next() {
        let trimmed = line.trim_start();
        let Some(lang) = trimmed.strip_prefix("```") else {
            if !line.trim().is_empty() {
                previous = line.trim();
            }
            continue;
        };
        let indent = line.len() - trimmed.len();
        let mut text = String::new();
        for (_, l) in lines.by_ref() {
            if l.trim() == "```" {
                break;
            }
            text.push_str(l.get(indent..).unwrap_or(l.trim_start()));
            text.push('\n');
        }
        let marker = previous
            .strip_prefix("<!-- example:")
            .and_then(|m| m.strip_suffix("-->"))
            .map(|m| m.trim().to_string());
        out.push(Block {
            line: i + 1,
            lang: lang.trim().to_string(),
            text,
            marker,
        });
        previous = "";
    }
    out
}

/// README.md and every page of the guide (not the rendered book).
fn pages() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() && path.file_name().is_some_and(|n| n != "book") {
                walk(&path, out);
            } else if path.extension().is_some_and(|e| e == "md") {
                out.push(path);
            }
        }
    }
    let mut out = vec![Path::new(ROOT).join("README.md")];
    walk(&Path::new(ROOT).join("docs"), &mut out);
    out.sort();
    out
}

/// A fresh working folder for one page, laid out like the repository root.
fn workdir(page: &Path) -> PathBuf {
    let rel = page
        .strip_prefix(ROOT)
        .unwrap()
        .to_string_lossy()
        .replace('/', "-");
    let dir = std::env::temp_dir().join(format!("bw-examples-{}-{rel}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for name in ["config", "recordings", "tests", "deploy"] {
        std::os::unix::fs::symlink(Path::new(ROOT).join(name), dir.join(name)).unwrap();
    }
    dir
}

/// A shell in `dir` with `boltwatch` first on the `PATH`.
fn shell(dir: &Path, script: &str) -> Command {
    let bin = Path::new(env!("CARGO_BIN_EXE_boltwatch")).parent().unwrap();
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let mut cmd = Command::new("bash");
    cmd.args(["-euo", "pipefail", "-c", script])
        .current_dir(dir)
        .env("PATH", path)
        .env("XDG_STATE_HOME", dir.join("state"))
        .env_remove("RUST_LOG");
    cmd
}

/// Runs a block to its end (at most [`BLOCK_TIMEOUT`]).
fn run_block(dir: &Path, script: &str) -> Output {
    let mut child = shell(dir, script)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("bash runs");
    // Drain both pipes while waiting, so a chatty example cannot block on a full pipe.
    let mut out = child.stdout.take().unwrap();
    let mut err = child.stderr.take().unwrap();
    let out_thread = std::thread::spawn(move || {
        let mut v = Vec::new();
        out.read_to_end(&mut v).map(|_| v)
    });
    let err_thread = std::thread::spawn(move || {
        let mut v = Vec::new();
        err.read_to_end(&mut v).map(|_| v)
    });
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > BLOCK_TIMEOUT {
            let _ = child.kill();
            panic!("example still running after {BLOCK_TIMEOUT:?}:\n{script}");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    Output {
        status,
        stdout: out_thread.join().unwrap().unwrap(),
        stderr: err_thread.join().unwrap().unwrap(),
    }
}

/// A background daemon, killed if a failing example ends the page early (else it would
/// outlive the test and hold the default ports).
struct Daemon(Option<Child>);

impl Drop for Daemon {
    fn drop(&mut self) {
        if let Some(mut child) = self.0.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// `boltwatch run` in the background, once its metrics port answers.
fn start_daemon(dir: &Path) -> Daemon {
    let log = std::fs::File::create(dir.join("daemon.log")).unwrap();
    let mut daemon = Daemon(Some(
        shell(dir, "exec boltwatch run")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("daemon starts"),
    ));
    let start = Instant::now();
    while TcpStream::connect("127.0.0.1:9464").is_err() {
        let exited = daemon.0.as_mut().and_then(|c| c.try_wait().ok().flatten());
        assert!(
            exited.is_none(),
            "the daemon exited ({exited:?}) before serving; its log:\n{}",
            std::fs::read_to_string(dir.join("daemon.log")).unwrap_or_default()
        );
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "the daemon's metrics never answered; its log:\n{}",
            std::fs::read_to_string(dir.join("daemon.log")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // The port answered: ours, not another daemon's (which would leave ours without one).
    std::thread::sleep(Duration::from_millis(300));
    let exited = daemon.0.as_mut().and_then(|c| c.try_wait().ok().flatten());
    assert!(
        exited.is_none(),
        "the daemon exited ({exited:?}): is another one using the default ports? Its log:\n{}",
        std::fs::read_to_string(dir.join("daemon.log")).unwrap_or_default()
    );
    daemon
}

/// SIGINT, as Ctrl-C: the daemon must stop cleanly (exit 0) within a minute.
fn stop_daemon(mut daemon: Daemon, dir: &Path, where_: &str) {
    let mut child = daemon.0.take().expect("a running daemon");
    unsafe {
        libc::kill(child.id() as i32, libc::SIGINT);
    }
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            panic!("{where_}: the daemon did not stop on SIGINT");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(
        status.success(),
        "{where_}: the daemon exited with {status}; its log:\n{}",
        std::fs::read_to_string(dir.join("daemon.log")).unwrap_or_default()
    );
}

/// The lines of an output block, but for `...`, appear in `stdout` in order.
fn check_output(expected: &str, stdout: &str, where_: &str) {
    let mut rest = stdout.lines().map(str::trim_end);
    for want in expected.lines().map(str::trim_end) {
        if want.trim() == "..." || want.is_empty() {
            continue;
        }
        assert!(
            rest.any(|got| got == want),
            "{where_}: the output lacks (in this order) the line\n{want}\nstdout was:\n{stdout}"
        );
    }
}

/// Runs one page's examples; returns (run, not run).
fn run_page(page: &Path) -> (usize, usize) {
    let name = page.strip_prefix(ROOT).unwrap().display().to_string();
    let text = std::fs::read_to_string(page).unwrap();
    let dir = workdir(page);
    let (mut ran, mut skipped) = (0, 0);
    let mut daemon = None;
    let mut last_stdout: Option<String> = None;
    for b in blocks(&text) {
        let where_ = format!("{name}:{}", b.line);
        let marker = b.marker.as_deref().unwrap_or("");
        if b.lang == "text" && marker == "output" {
            let stdout = last_stdout
                .as_deref()
                .expect("an output block follows an example");
            check_output(&b.text, stdout, &where_);
            continue;
        }
        if b.lang != "sh" {
            continue;
        }
        if let Some(reason) = marker.strip_prefix("not run,") {
            assert!(!reason.trim().is_empty(), "{where_}: say why it is not run");
            skipped += 1;
            continue;
        }
        assert!(marker.is_empty(), "{where_}: unknown marker {marker:?}");
        ran += 1;
        if b.text.trim() == "boltwatch run" {
            if let Some(d) = daemon.take() {
                stop_daemon(d, &dir, &where_);
            }
            daemon = Some(start_daemon(&dir));
            continue;
        }
        let started = Instant::now();
        let out = run_block(&dir, &b.text);
        let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "{where_}: the example failed ({}):\n{}\nstderr:\n{}",
            out.status,
            b.text,
            String::from_utf8_lossy(&out.stderr)
        );
        eprintln!("{where_}: {:.1} s", started.elapsed().as_secs_f64());
        last_stdout = Some(stdout);
    }
    if let Some(d) = daemon {
        stop_daemon(d, &dir, &name);
    }
    let _ = std::fs::remove_dir_all(&dir);
    (ran, skipped)
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow tier: cargo test --features slow-tests"
)]
fn every_shell_example_in_the_readme_and_the_guide_runs() {
    // `BOLTWATCH_EXAMPLES=docs/models.md` runs the pages whose path contains that text.
    let only = std::env::var("BOLTWATCH_EXAMPLES").unwrap_or_default();
    let (mut ran, mut skipped) = (0, 0);
    for page in pages()
        .into_iter()
        .filter(|p| p.to_string_lossy().contains(&only))
    {
        let (r, s) = run_page(&page);
        ran += r;
        skipped += s;
    }
    eprintln!("{ran} examples run, {skipped} marked not run");
    // Every page: a floor on the count, so a harness that stops reading a layout fails.
    assert!(
        ran >= if only.is_empty() { 40 } else { 1 },
        "only {ran} examples found: is the page layout still read?"
    );
}

#[test]
fn the_example_parser_reads_markers_fences_and_indented_blocks() {
    let page = "text\n<!-- example: not run, a daemon -->\n```sh\nboltwatch run\n```\n\n\
                1. a step:\n\n   ```sh\n   boltwatch modes \\\n     -o m.json\n   ```\n\
                <!-- example: output -->\n```text\nline\n```\n";
    let b = blocks(page);
    assert_eq!(b.len(), 3);
    assert_eq!(b[0].marker.as_deref(), Some("not run, a daemon"));
    assert_eq!((b[0].line, b[0].lang.as_str()), (3, "sh"));
    assert_eq!(b[1].text, "boltwatch modes \\\n  -o m.json\n");
    assert_eq!(b[1].marker, None);
    assert_eq!(b[2].marker.as_deref(), Some("output"));
    check_output("a\n...\nc\n", "a\nb\nc\n", "here");
}

#[test]
#[should_panic(expected = "lacks")]
fn an_output_line_out_of_order_fails() {
    check_output("c\na\n", "a\nb\nc\n", "here");
}
