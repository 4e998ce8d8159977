//! Non-finite numbers in JSON payloads: `NaN`, `Infinity` and overflowing literals are not
//! JSON, so the parser would reject the whole payload without saying where. A sanitizing
//! pass replaces each by a marker string first, and validation names the field it sits in.

use serde_json::Value;

/// Prefix of the string the sanitizing pass substitutes for a non-finite number token. It
/// starts with NUL so no sensible string value collides with it.
pub(super) const NONFINITE_MARKER: &str = "\u{0}boltwatch-nonfinite:";

/// The original token of a non-finite number replaced by [`sanitize`], if `v` is one.
pub(super) fn nonfinite_token(v: &Value) -> Option<&str> {
    v.as_str()?.strip_prefix(NONFINITE_MARKER)
}

pub(super) fn nonfinite_reason(token: &str) -> String {
    match token {
        "NaN" | "Infinity" | "-Infinity" => format!("not a finite number ({token})"),
        _ => format!("not a finite number ({token} overflows f64)"),
    }
}

/// Replaces the bare tokens `NaN`, `Infinity` and `-Infinity`, and number literals that
/// overflow f64 (`1e999`), outside string literals, by a marker string the JSON parser
/// accepts (`"\u0000boltwatch-nonfinite:<token>"`), so the walk can name the field.
/// Everything else, in particular string contents, is copied unchanged.
pub(super) fn sanitize(text: &str) -> std::borrow::Cow<'_, str> {
    if !may_hold_nonfinite(text) {
        return std::borrow::Cow::Borrowed(text);
    }
    std::borrow::Cow::Owned(sanitize_tokens(text))
}

/// Whether `text` may hold a non-finite literal: `NaN`, `Infinity`, an exponent of three
/// or more digits, or a run of over 300 digits (anything else is a finite f64). A cheap
/// scan that lets the common payload skip [`sanitize_tokens`].
pub(super) fn may_hold_nonfinite(text: &str) -> bool {
    if text.contains("NaN") || text.contains("Infinity") {
        return true;
    }
    let b = text.as_bytes();
    let mut digits = 0;
    for (i, &c) in b.iter().enumerate() {
        if c.is_ascii_digit() {
            digits += 1;
            if digits > 300 {
                return true;
            }
            continue;
        }
        digits = 0;
        if c == b'e' || c == b'E' {
            let rest = &b[i + 1..];
            let rest = rest
                .strip_prefix(b"+")
                .or_else(|| rest.strip_prefix(b"-"))
                .unwrap_or(rest);
            if rest.iter().take(3).filter(|d| d.is_ascii_digit()).count() == 3 {
                return true;
            }
        }
    }
    false
}

pub(super) fn sanitize_tokens(text: &str) -> String {
    let bytes = text.as_bytes();
    let mut out = String::with_capacity(text.len() + 16);
    let mut copied = 0; // bytes of `text` already in `out`
    let mut in_string = false;
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if in_string {
            match c {
                b'\\' => i += 2,
                b'"' => {
                    in_string = false;
                    i += 1;
                }
                _ => i += 1,
            }
            continue;
        }
        match c {
            b'"' => {
                in_string = true;
                i += 1;
            }
            b'N' | b'I' | b'-' | b'0'..=b'9' => {
                // A bare token: letters, digits and the number punctuation. It ends on an
                // ASCII byte or at the end, so `i..end` lies on char boundaries.
                let mut end = i + 1;
                while end < bytes.len()
                    && (bytes[end].is_ascii_alphanumeric()
                        || matches!(bytes[end], b'+' | b'-' | b'.'))
                {
                    end += 1;
                }
                let token = text.get(i..end).unwrap_or("");
                // A decimal literal overflows to ±∞ only with an exponent or over 300
                // digits; the others need no trial parse.
                let replace = match token {
                    "NaN" | "Infinity" | "-Infinity" => true,
                    _ if token.len() > 300 || token.contains(['e', 'E']) => {
                        token.parse::<f64>().is_ok_and(f64::is_infinite)
                    }
                    _ => false,
                };
                if replace {
                    out.push_str(text.get(copied..i).unwrap_or(""));
                    out.push('"');
                    out.push_str("\\u0000");
                    out.push_str(NONFINITE_MARKER.trim_start_matches('\u{0}'));
                    out.push_str(token);
                    out.push('"');
                    copied = end;
                }
                i = end;
            }
            _ => i += 1,
        }
    }
    out.push_str(text.get(copied..).unwrap_or(""));
    out
}
