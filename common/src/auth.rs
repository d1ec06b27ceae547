//! The shared token that actors present to the learner on every RPC, when a run asks for one.
//!
//! The token comes from a file (`server.auth_token_file` on the learner, `--auth-token-file` on
//! actors) or the `JUNCTION_AUTH_TOKEN` environment variable, never from the run
//! configuration itself: that is written to run directories and checkpoints.

use std::path::Path;

/// Environment variable that holds the token (e.g. from a Kubernetes Secret).
pub const TOKEN_ENV: &str = "JUNCTION_AUTH_TOKEN";
/// gRPC metadata key that carries `Bearer <token>`.
pub const HEADER: &str = "authorization";
const SCHEME: &str = "Bearer ";
/// Shorter tokens are refused: they would be guessable.
pub const MIN_TOKEN_BYTES: usize = 16;
/// Longer tokens are refused: HTTP/2 header limits would cut them off.
pub const MAX_TOKEN_BYTES: usize = 4096;

#[derive(Debug, thiserror::Error)]
pub enum AuthError {
    #[error("cannot read the token file {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("both {TOKEN_ENV} and a token file are set; set one (they would have to agree anyway)")]
    TwoSources,
    #[error(
        "the auth token from {origin} must be {MIN_TOKEN_BYTES} to {MAX_TOKEN_BYTES} visible ASCII characters (got {len} bytes)"
    )]
    Invalid { origin: String, len: usize },
}

/// A shared secret; `Debug` does not print it.
#[derive(Clone, PartialEq, Eq)]
pub struct Token(String);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Token(<{} bytes>)", self.0.len())
    }
}

impl Token {
    /// Checks a token read from `origin`: surrounding whitespace (a file's trailing newline)
    /// is dropped, the rest must be visible ASCII of a sensible length.
    pub fn new(text: &str, origin: &str) -> Result<Token, AuthError> {
        let text = text.trim();
        let valid = (MIN_TOKEN_BYTES..=MAX_TOKEN_BYTES).contains(&text.len())
            && text.bytes().all(|b| b.is_ascii_graphic());
        if valid {
            Ok(Token(text.to_string()))
        } else {
            Err(AuthError::Invalid {
                origin: origin.to_string(),
                len: text.len(),
            })
        }
    }

    /// The token from `file` (if given) or the environment (if set); `None` when neither is.
    pub fn load(file: Option<&Path>) -> Result<Option<Token>, AuthError> {
        let env = std::env::var(TOKEN_ENV).ok().filter(|v| !v.is_empty());
        match (file, env) {
            (Some(_), Some(_)) => Err(AuthError::TwoSources),
            (Some(path), None) => {
                let text = std::fs::read_to_string(path).map_err(|source| AuthError::Read {
                    path: path.display().to_string(),
                    source,
                })?;
                Token::new(&text, &path.display().to_string()).map(Some)
            }
            (None, Some(value)) => Token::new(&value, TOKEN_ENV).map(Some),
            (None, None) => Ok(None),
        }
    }

    /// The value of the `authorization` header a client sends.
    pub fn header_value(&self) -> String {
        format!("{SCHEME}{}", self.0)
    }

    /// Does `header` (an `authorization` value) carry this token? Takes the same time for
    /// every header of a given length, so timing does not reveal how much of a guess was
    /// right.
    pub fn accepts(&self, header: &[u8]) -> bool {
        let expected = self.header_value();
        constant_time_eq(expected.as_bytes(), header)
    }
}

/// Byte-wise equality whose running time depends only on the lengths.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    let difference = a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y));
    // Keeps the optimiser from turning the fold into an early-exit comparison.
    std::hint::black_box(difference) == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_are_trimmed_checked_and_compared_exactly() {
        let token = Token::new("  0123456789abcdef-secret\n", "test").unwrap();
        assert!(token.accepts(b"Bearer 0123456789abcdef-secret"));
        assert!(!token.accepts(b"Bearer 0123456789abcdef-secreT"));
        assert!(!token.accepts(b"Bearer 0123456789abcdef-secre"));
        assert!(!token.accepts(b"0123456789abcdef-secret"));
        assert!(!token.accepts(b""));
        assert!(matches!(
            Token::new("short", "test"),
            Err(AuthError::Invalid { len: 5, .. })
        ));
        assert!(Token::new("has a space inside it", "test").is_err());
        assert!(Token::new(&"x".repeat(MAX_TOKEN_BYTES + 1), "test").is_err());
        assert!(!format!("{token:?}").contains("secret"), "Debug hides it");
    }

    #[test]
    fn constant_time_eq_is_equality() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"ab"));
        assert!(constant_time_eq(b"", b""));
    }
}
