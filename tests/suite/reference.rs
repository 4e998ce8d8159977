//! The reference pages agree with the program: `docs/reference/configuration.md` lists every
//! key of the bundled `config/default.toml` with its default, and nothing else;
//! `docs/reference/commands.md` lists every option each command's `--help` shows, with the
//! same defaults, and nothing else.

use std::collections::BTreeMap;
use std::process::Command;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

fn read(rel: &str) -> String {
    std::fs::read_to_string(format!("{ROOT}/{rel}")).unwrap()
}

/// The cells of a Markdown table row, trimmed (`\|` inside a cell kept as `|`).
fn cells(line: &str) -> Vec<String> {
    let inner = line.trim().trim_start_matches('|').trim_end_matches('|');
    inner
        .replace("\\|", "\u{1}")
        .split('|')
        .map(|c| c.trim().replace('\u{1}', "|"))
        .collect()
}

/// The text between the first pair of backticks of a cell, if the cell is just that.
fn code(cell: &str) -> Option<&str> {
    cell.strip_prefix('`')?.strip_suffix('`')
}

/// Every key of a TOML table as `section.key` (an array of tables by its name), with its
/// value.
fn flatten(prefix: &str, table: &toml::Table, out: &mut BTreeMap<String, toml::Value>) {
    for (k, v) in table {
        let path = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match v {
            toml::Value::Table(t) => flatten(&path, t, out),
            toml::Value::Array(a) if a.iter().all(|x| x.is_table()) && !a.is_empty() => {
                for x in a {
                    flatten(&path, x.as_table().unwrap(), out);
                }
            }
            _ => {
                out.insert(path, v.clone());
            }
        }
    }
}

/// The documented keys of configuration.md: `section.key` → the default cell.
fn documented_keys() -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let mut section = String::new();
    for line in read("docs/reference/configuration.md").lines() {
        if let Some(h) = line.strip_prefix("## `[") {
            section = h.trim_end_matches("`").trim_matches(['[', ']']).to_string();
        } else if line.starts_with("| `") && !section.is_empty() {
            let c = cells(line);
            let key = code(&c[0]).expect("a key cell is code");
            let prev = out.insert(format!("{section}.{key}"), c[1].clone());
            assert!(prev.is_none(), "{section}.{key} documented twice");
        }
    }
    out
}

/// TOML values compared as numbers where both are numbers (`0.10` is `0.1`, `20` is `20.0`).
fn same_value(a: &toml::Value, b: &toml::Value) -> bool {
    let num = |v: &toml::Value| v.as_float().or(v.as_integer().map(|i| i as f64));
    match (a, b) {
        (toml::Value::Array(x), toml::Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(p, q)| same_value(p, q))
        }
        _ => match (num(a), num(b)) {
            (Some(p), Some(q)) => p == q,
            _ => a == b,
        },
    }
}

#[test]
fn every_configuration_key_is_documented_with_its_default() {
    let text = read("config/default.toml");
    let defaults: toml::Table = text.parse().unwrap();
    let mut keys = BTreeMap::new();
    flatten("", &defaults, &mut keys);
    let documented = documented_keys();
    for (key, value) in &keys {
        let cell = documented
            .get(key)
            .unwrap_or_else(|| panic!("{key} is in config/default.toml, not in configuration.md"));
        let doc = code(cell).unwrap_or_else(|| panic!("{key}: default {cell:?} is not code"));
        let parsed: toml::Table = format!("v = {doc}")
            .parse()
            .unwrap_or_else(|e| panic!("{key}: documented default {doc} is not TOML: {e}"));
        assert!(
            same_value(&parsed["v"], value),
            "{key}: documented default {doc}, config/default.toml has {value}"
        );
    }
    for (key, cell) in &documented {
        if keys.contains_key(key) {
            continue;
        }
        // A key without a default is named, commented out, in the file.
        assert_eq!(
            cell, "absent",
            "{key} is documented but not in config/default.toml"
        );
        let name = key.rsplit('.').next().unwrap();
        assert!(
            text.lines()
                .any(|l| l.trim_start().starts_with('#') && l.contains(name)),
            "{key} is documented as absent but config/default.toml never names it"
        );
    }
}

/// The long options of `boltwatch <args> --help`, with their `[default: …]` if shown.
fn help_options(args: &[&str]) -> BTreeMap<String, Option<String>> {
    let out = Command::new(env!("CARGO_BIN_EXE_boltwatch"))
        .args(args)
        .arg("--help")
        .output()
        .unwrap();
    assert!(out.status.success(), "boltwatch {args:?} --help");
    let text = String::from_utf8(out.stdout).unwrap();
    let mut opts = BTreeMap::new();
    let mut current: Option<String> = None;
    for line in text.lines() {
        let t = line.trim_start();
        // `-o, --out <OUT>`: the long name after a short one.
        let b = t.as_bytes();
        let t = if b.len() > 4 && b[0] == b'-' && b[1] != b'-' && &b[2..4] == b", " {
            &t[4..]
        } else {
            t
        };
        if let Some(rest) = t.strip_prefix("--").filter(|_| line.starts_with("  ")) {
            let name: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
                .collect();
            if name != "help" && name != "version" {
                opts.insert(name.clone(), None);
                current = Some(name);
            } else {
                current = None;
            }
        }
        if let (Some(name), Some(i)) = (&current, line.find("[default: ")) {
            let d = &line[i + 10..];
            opts.insert(name.clone(), Some(d[..d.find(']').unwrap()].to_string()));
        }
    }
    opts
}

/// The options commands.md documents for each command: option → default cell.
fn documented_options() -> BTreeMap<String, BTreeMap<String, String>> {
    let mut out: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    let mut command = String::new();
    for line in read("docs/reference/commands.md").lines() {
        if let Some(h) = line.strip_prefix("## `") {
            command = h.split([' ', '`']).next().unwrap().to_string();
        } else if line.starts_with("| `") && !command.is_empty() {
            let c = cells(line);
            for part in c[0].split('`').filter(|p| p.contains("--")) {
                let name = part[part.find("--").unwrap() + 2..]
                    .split(' ')
                    .next()
                    .unwrap()
                    .to_string();
                let entry = out.entry(command.clone()).or_default();
                entry.insert(name, c[1].clone());
            }
        }
    }
    out
}

#[test]
fn every_command_option_is_documented_with_its_default() {
    let documented = documented_options();
    let commands = [
        "simulate",
        "modes",
        "update",
        "sweep-sigma",
        "diagnose",
        "scenario",
        "replay",
        "report",
        "run",
        "publish",
        "export-matrices",
        "identify",
        "normalisation",
        "plan",
    ];
    for command in commands {
        let mut help = BTreeMap::new();
        if command == "normalisation" {
            help.extend(help_options(&[command, "show"]));
            help.extend(help_options(&[command, "learn"]));
        } else {
            help = help_options(&[command]);
        }
        let docs = documented.get(command).cloned().unwrap_or_default();
        for (name, default) in &help {
            let cell = docs
                .get(name)
                .unwrap_or_else(|| panic!("{command} --{name} is not in commands.md"));
            if let (Some(d), Some(c)) = (default, code(cell)) {
                // Numbers compare as numbers (`1.0` is clap's `1`).
                let same = match (c.parse::<f64>(), d.parse::<f64>()) {
                    (Ok(x), Ok(y)) => x == y,
                    _ => c == d,
                };
                assert!(
                    same,
                    "{command} --{name}: documented default {c}, --help {d}"
                );
            }
        }
        for name in docs.keys() {
            assert!(
                help.contains_key(name),
                "commands.md documents {command} --{name}, which --help does not show"
            );
        }
    }
}

/// The items a code span names: `a::b::C::{f, g}` → `f`, `g`; `a::b::f` → `f`; an enum's
/// variant `a::E::V` → `E` (with the variant checked by the caller).
fn named_items(span: &str) -> Vec<(String, Option<String>)> {
    let ident = |s: &str| -> String {
        s.trim()
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect()
    };
    if let Some((_, group)) = span.split_once("::{") {
        return group
            .trim_end_matches('}')
            .split(',')
            .map(|g| (ident(g), None))
            .collect();
    }
    let parts: Vec<String> = span.split("::").map(ident).collect();
    let upper = |s: &str| s.starts_with(|c: char| c.is_uppercase());
    match parts.as_slice() {
        [.., ty, variant] if upper(ty) && upper(variant) => {
            vec![(ty.clone(), Some(variant.clone()))]
        }
        [.., last] => vec![(last.clone(), None)],
        [] => Vec::new(),
    }
}

/// The text of a file, or of every `.rs` file under a folder.
fn source_of(rel: &str) -> String {
    let path = std::path::Path::new(ROOT).join(rel);
    if path.is_file() {
        return std::fs::read_to_string(path).unwrap();
    }
    assert!(
        path.is_dir(),
        "docs/paper.md names {rel}, which does not exist"
    );
    let mut out = String::new();
    for entry in std::fs::read_dir(&path).unwrap() {
        let p = entry.unwrap().path();
        let rel = p.strip_prefix(ROOT).unwrap().to_string_lossy().into_owned();
        if p.is_dir() || p.extension().is_some_and(|e| e == "rs") {
            out += &source_of(&rel);
        }
    }
    out
}

/// Whether `item` is defined (`fn`, `struct`, `enum`, `trait`, `type`, `const`) in `src`.
fn defines(src: &str, item: &str) -> bool {
    ["fn", "struct", "enum", "trait", "type", "const"]
        .iter()
        .any(|kw| {
            ["(", " ", "<", ":"]
                .iter()
                .any(|e| src.contains(&format!("{kw} {item}{e}")))
        })
}

/// `docs/paper.md` maps each equation to the functions that implement it and their files:
/// every file (or folder) exists, and every item named (`a::b::f`, `Type::{f, g}`, an
/// enum's variant) is defined in one of the row's files.
#[test]
fn every_function_the_paper_map_names_is_in_its_file() {
    let mut checked = 0;
    for line in read("docs/paper.md").lines() {
        if !line.starts_with('|') || !line.contains("`src/") {
            continue;
        }
        let c = cells(line);
        let (functions, files) = (&c[c.len() - 2], &c[c.len() - 1]);
        let src: String = files
            .split('`')
            .filter(|p| p.starts_with("src/"))
            .map(source_of)
            .collect();
        for span in functions.split('`').skip(1).step_by(2) {
            if !span.contains("::") || span.contains(' ') {
                continue;
            }
            for (item, variant) in named_items(span) {
                // A module is named by its file or declared in a file of the row.
                let module = files.contains(&format!("/{item}.rs`"))
                    || files.contains(&format!("/{item}/`"))
                    || src.contains(&format!("mod {item};"));
                let ok = (module || defines(&src, &item))
                    && variant.as_ref().is_none_or(|v| {
                        src.contains(&format!("{v},"))
                            || src.contains(&format!("{v} {{"))
                            || src.contains(&format!("{v}("))
                    });
                assert!(ok, "docs/paper.md: `{span}` is not defined in {files}");
                checked += 1;
            }
        }
    }
    assert!(
        checked > 30,
        "only {checked} items checked: is the table still read?"
    );
}
