//! Optional protection of the gRPC port for runs across hosts: TLS (rustls) and a shared
//! token checked on every RPC before it reaches a handler.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use prometheus::IntCounterVec;
use tonic::service::Interceptor;
use tonic::transport::{Certificate, Identity, ServerTlsConfig};
use tonic::{Request, Status};

use junction_common::auth::{self, AuthError, Token};
use junction_core::config::ServerSection;

use crate::telemetry::labels::REFUSED_UNAUTHENTICATED;

#[derive(Debug, thiserror::Error)]
pub enum SecurityError {
    #[error("cannot read {key} = {path}: {source}")]
    Read {
        key: &'static str,
        path: String,
        source: std::io::Error,
    },
    #[error("{key} = {path} holds no PEM {what}")]
    Pem {
        key: &'static str,
        path: String,
        what: &'static str,
    },
    #[error(transparent)]
    Token(#[from] AuthError),
}

/// What a PEM file must hold.
#[derive(Clone, Copy)]
enum Pem {
    Certificate,
    PrivateKey,
}

fn read_pem(key: &'static str, value: &str, kind: Pem) -> Result<Option<Vec<u8>>, SecurityError> {
    let Some(path) = ServerSection::path(value) else {
        return Ok(None);
    };
    let bytes = std::fs::read(path).map_err(|source| SecurityError::Read {
        key,
        path: value.to_string(),
        source,
    })?;
    // rustls would only complain when the first actor connects; say it at start.
    let text = String::from_utf8_lossy(&bytes);
    let (found, what) = match kind {
        Pem::Certificate => (text.contains("-----BEGIN CERTIFICATE-----"), "certificate"),
        Pem::PrivateKey => (text.contains("PRIVATE KEY-----"), "private key"),
    };
    if !found {
        return Err(SecurityError::Pem {
            key,
            path: value.to_string(),
            what,
        });
    }
    Ok(Some(bytes))
}

/// The server's TLS settings from `[server]`, or `None` for plain TCP.
pub fn server_tls(server: &ServerSection) -> Result<Option<ServerTlsConfig>, SecurityError> {
    let cert = read_pem("server.tls_cert", &server.tls_cert, Pem::Certificate)?;
    let key = read_pem("server.tls_key", &server.tls_key, Pem::PrivateKey)?;
    let client_ca = read_pem(
        "server.tls_client_ca",
        &server.tls_client_ca,
        Pem::Certificate,
    )?;
    let (Some(cert), Some(key)) = (cert, key) else {
        // Config validation requires both or neither.
        return Ok(None);
    };
    let mut tls = ServerTlsConfig::new().identity(Identity::from_pem(cert, key));
    if let Some(ca) = client_ca {
        tls = tls.client_ca_root(Certificate::from_pem(ca));
    }
    Ok(Some(tls))
}

/// The shared token from `server.auth_token_file` or `JUNCTION_AUTH_TOKEN`, if either is set.
pub fn server_token(server: &ServerSection) -> Result<Option<Token>, SecurityError> {
    Ok(Token::load(ServerSection::path(&server.auth_token_file))?)
}

/// Refuses every RPC without the run's token with UNAUTHENTICATED (and counts it); lets
/// everything through when the run has no token.
#[derive(Clone)]
pub struct TokenCheck {
    token: Option<Arc<Token>>,
    refused: IntCounterVec,
    /// The first refusal logs at warn, later ones at debug (a guesser must not flood logs).
    logged: Arc<AtomicBool>,
}

impl TokenCheck {
    pub fn new(token: Option<Token>, refused: IntCounterVec) -> Self {
        TokenCheck {
            token: token.map(Arc::new),
            refused,
            logged: Arc::new(AtomicBool::new(false)),
        }
    }
}

impl Interceptor for TokenCheck {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(token) = &self.token else {
            return Ok(request);
        };
        let message = match request.metadata().get(auth::HEADER) {
            Some(value) if token.accepts(value.as_bytes()) => return Ok(request),
            Some(_) => "wrong auth token",
            None => {
                "missing auth token: this learner requires one (actor --auth-token-file or JUNCTION_AUTH_TOKEN)"
            }
        };
        self.refused
            .with_label_values(&[REFUSED_UNAUTHENTICATED])
            .inc();
        let peer = request
            .remote_addr()
            .map(|a| a.to_string())
            .unwrap_or_else(|| "?".into());
        if self.logged.swap(true, Ordering::Relaxed) {
            tracing::debug!(peer, "refused an RPC: {message}");
        } else {
            tracing::warn!(
                peer,
                "refused an RPC: {message} (further refusals log at debug; counted in junction_learner_requests_refused_total)"
            );
        }
        Err(Status::unauthenticated(message))
    }
}
