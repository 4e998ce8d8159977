//! Who may read the console: HTTP basic authentication against a password file of
//! `user:bcrypt-hash` lines (what `htpasswd -nB user` prints), and HTTPS from a PEM
//! certificate and key. Both are optional; without them the console should stay on
//! loopback or behind a reverse proxy that does this.

use std::collections::{HashMap, HashSet};
use std::path::Path;
use std::sync::{Arc, Mutex};

use anyhow::{Context, Result, bail};
use axum::extract::{Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::{Html, IntoResponse, Response};
use base64::Engine as _;
use sha2::{Digest, Sha256};

/// At most this many verified credentials are remembered (bcrypt takes tens of ms a try,
/// and a live page asks several times a minute).
const REMEMBERED: usize = 64;

/// The users of a password file.
pub struct Users {
    hashes: HashMap<String, String>,
    /// A hash of no one's password at the file's first cost: an unknown user costs what a
    /// known one does.
    nobody: String,
    /// SHA-256 of `Authorization` headers already verified.
    verified: Mutex<HashSet<[u8; 32]>>,
}

impl Users {
    /// Reads `path`: one `user:hash` per line, `#` comments and blank lines allowed; every
    /// hash must be bcrypt (`$2a$`, `$2b$` or `$2y$`).
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| {
            format!(
                "configuration key console.users_file: cannot read {}",
                path.display()
            )
        })?;
        let mut hashes = HashMap::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let at = || format!("{} line {}", path.display(), i + 1);
            let Some((user, hash)) = line.split_once(':') else {
                bail!("{}: not user:hash", at());
            };
            if !["$2a$", "$2b$", "$2y$"].iter().any(|p| hash.starts_with(p)) {
                bail!(
                    "{}: the hash of `{user}` is not bcrypt (make it with htpasswd -nB)",
                    at()
                );
            }
            if hashes.insert(user.to_string(), hash.to_string()).is_some() {
                bail!("{}: user `{user}` is listed twice", at());
            }
        }
        let Some(first) = hashes.values().next() else {
            bail!("{} lists no user", path.display());
        };
        let cost = first.get(4..6).and_then(|c| c.parse().ok()).unwrap_or(10);
        let nobody = bcrypt::hash(rand_password(), cost).context("bcrypt")?;
        Ok(Self {
            hashes,
            nobody,
            verified: Mutex::new(HashSet::new()),
        })
    }

    /// Whether the `Authorization` header value names a user and its password.
    fn admits(&self, authorization: &[u8]) -> bool {
        let key: [u8; 32] = Sha256::digest(authorization).into();
        if self.verified.lock().is_ok_and(|v| v.contains(&key)) {
            return true;
        }
        let Some((user, password)) = basic_credentials(authorization) else {
            return false;
        };
        let (hash, known) = match self.hashes.get(&user) {
            Some(h) => (h.as_str(), true),
            None => (self.nobody.as_str(), false),
        };
        let ok = bcrypt::verify(password.as_bytes(), hash).unwrap_or(false) && known;
        if ok && let Ok(mut v) = self.verified.lock() {
            if v.len() >= REMEMBERED {
                v.clear();
            }
            v.insert(key);
        }
        ok
    }
}

/// A password no one knows (this process's address space and time, hashed).
fn rand_password() -> String {
    let seed = format!("{:?}{:p}", std::time::SystemTime::now(), &REMEMBERED);
    format!("{:x}", Sha256::digest(seed.as_bytes()))
}

/// `Basic base64(user:password)` decoded.
fn basic_credentials(authorization: &[u8]) -> Option<(String, String)> {
    let text = std::str::from_utf8(authorization).ok()?;
    let (scheme, token) = text.trim().split_once(' ')?;
    if !scheme.eq_ignore_ascii_case("basic") {
        return None;
    }
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(token.trim())
        .ok()?;
    let text = String::from_utf8(bytes).ok()?;
    let (user, password) = text.split_once(':')?;
    Some((user.to_string(), password.to_string()))
}

/// Lets a request through when no password file is configured or its credentials verify;
/// else 401 with the challenge.
pub async fn require(
    State(users): State<Option<Arc<Users>>>,
    req: Request,
    next: Next,
) -> Response {
    let Some(users) = users else {
        return next.run(req).await;
    };
    let given = req
        .headers()
        .get(header::AUTHORIZATION)
        .map(|v| v.as_bytes().to_vec());
    let ok = match given {
        Some(a) => tokio::task::spawn_blocking(move || users.admits(&a))
            .await
            .unwrap_or(false),
        None => false,
    };
    if ok {
        return next.run(req).await;
    }
    let mut r = (
        StatusCode::UNAUTHORIZED,
        Html(super::pages::message(
            "Unauthorised",
            "this console needs a user and password",
        )),
    )
        .into_response();
    r.headers_mut().insert(
        header::WWW_AUTHENTICATE,
        HeaderValue::from_static("Basic realm=\"boltwatch\", charset=\"UTF-8\""),
    );
    r
}

/// The TLS configuration of a PEM certificate chain and private key (ring's ciphers).
pub fn tls_config(cert: &Path, key: &Path) -> Result<axum_server::tls_rustls::RustlsConfig> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let chain = CertificateDer::pem_file_iter(cert)
        .and_then(|c| c.collect::<Result<Vec<_>, _>>())
        .with_context(|| format!("configuration key console.tls_cert: {}", cert.display()))?;
    let key_der = PrivateKeyDer::from_pem_file(key)
        .with_context(|| format!("configuration key console.tls_key: {}", key.display()))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()?
        .with_no_client_auth()
        .with_single_cert(chain, key_der)
        .context("configuration keys console.tls_cert and console.tls_key do not match")?;
    Ok(axum_server::tls_rustls::RustlsConfig::from_config(
        Arc::new(config),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(user: &str, password: &str) -> Vec<u8> {
        let token = base64::engine::general_purpose::STANDARD.encode(format!("{user}:{password}"));
        format!("Basic {token}").into_bytes()
    }

    /// A file of this test process's own, named `name`.
    fn scratch(name: &str) -> std::path::PathBuf {
        std::env::temp_dir().join(format!("bw-users-{name}-{}", std::process::id()))
    }

    #[test]
    fn a_user_is_admitted_with_its_password_only() {
        let file = scratch("ok");
        let hash = bcrypt::hash("s3cret: yes", 4).unwrap();
        std::fs::write(&file, format!("# operators\n\nana:{hash}\n")).unwrap();
        let users = Users::load(&file).unwrap();
        assert!(users.admits(&header("ana", "s3cret: yes")));
        assert!(users.admits(&header("ana", "s3cret: yes")), "remembered");
        assert!(!users.admits(&header("ana", "s3cret")));
        assert!(!users.admits(&header("bob", "s3cret: yes")));
        assert!(!users.admits(b"Bearer abc"));
        assert!(!users.admits(b"Basic !!!"));
        let _ = std::fs::remove_file(file);
    }

    #[test]
    fn a_password_file_that_is_not_bcrypt_is_refused_naming_the_line() {
        let file = scratch("bad");
        std::fs::write(&file, "ana:{SHA}abc\n").unwrap();
        let e = Users::load(&file).err().unwrap().to_string();
        assert!(e.contains("line 1") && e.contains("not bcrypt"), "{e}");
        std::fs::write(&file, "# nobody\n").unwrap();
        let e = Users::load(&file).err().unwrap().to_string();
        assert!(e.contains("no user"), "{e}");
        let _ = std::fs::remove_file(file);
    }
}
