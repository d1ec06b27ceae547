//! `[server]`: the learner's gRPC and metrics addresses, message and stream limits, TLS,
//! the auth token and shared memory.

use std::path::Path;

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServerSection {
    pub addr: String,
    pub metrics_addr: String,
    pub max_message_bytes: usize,
    pub max_concurrent_streams: u32,
    pub max_rollout_streams: usize,
    pub keepalive_interval_s: f64,
    pub keepalive_timeout_s: f64,
    pub tls_cert: String,
    pub tls_key: String,
    pub tls_client_ca: String,
    pub auth_token_file: String,
    /// Base name of the shared-memory services; empty: shared memory off.
    pub shm_name: String,
    pub shm_max_actors: usize,
}

impl ServerSection {
    /// A path key's value, `None` when empty (the feature is off).
    pub fn path(value: &str) -> Option<&Path> {
        (!value.trim().is_empty()).then(|| Path::new(value))
    }

    /// What is wrong with the section, one line per problem.
    pub(super) fn problems(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.max_message_bytes < 1 << 16 {
            problems.push("server.max_message_bytes must be >= 65536".to_string());
        }
        if self.max_concurrent_streams < 2 || self.max_rollout_streams == 0 {
            problems.push(
                "server.max_concurrent_streams must be >= 2 (an actor opens two streams) and server.max_rollout_streams > 0"
                    .to_string(),
            );
        }
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.keepalive_interval_s) || !positive(self.keepalive_timeout_s) {
            problems.push(
                "server.keepalive_interval_s and server.keepalive_timeout_s must be > 0"
                    .to_string(),
            );
        }
        let (cert, key) = (Self::path(&self.tls_cert), Self::path(&self.tls_key));
        if cert.is_some() != key.is_some() {
            problems.push("server.tls_cert and server.tls_key must be set together".to_string());
        }
        if Self::path(&self.tls_client_ca).is_some() && cert.is_none() {
            problems.push(
                "server.tls_client_ca (client certificates) needs server.tls_cert and server.tls_key"
                    .to_string(),
            );
        }
        if !self.shm_name.is_empty() && !is_valid_shm_name(&self.shm_name) {
            problems.push(format!(
                "server.shm_name {:?} may only hold letters, digits, '-', '_' and '.' (at most 200), or be \"\" for no shared memory",
                self.shm_name
            ));
        }
        if !(1..=1024).contains(&self.shm_max_actors) {
            problems.push("server.shm_max_actors must be in 1..=1024".to_string());
        }
        problems
    }
}

/// A base name for the shared-memory services (`server.shm_name`): 1 to 200 letters,
/// digits, '-', '_' or '.'.
pub fn is_valid_shm_name(base: &str) -> bool {
    (1..=200).contains(&base.len())
        && base
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
}
