//! The run's token and, optionally, TLS: what every rfcl gRPC call carries and every rfcl gRPC
//! service checks.
//!
//! * **Token.** One secret per run. Clients send it as `authorization: Bearer <token>` on every
//!   call ([`Stamp`]); services refuse a call without it or with another one with
//!   `UNAUTHENTICATED` before the handler runs, so a refused call changes nothing, and count the
//!   refusal ([`Guard::refused`]). The token comes from the environment, never from the command
//!   line (where `ps` shows it): `RFCL_TOKEN` holds it, or `RFCL_TOKEN_FILE` names a file that
//!   does (a Docker or Kubernetes secret). The standard `grpc.health.v1` service is the one
//!   exception: it tells only whether a service is serving, and container probes cannot send
//!   headers.
//! * **TLS** (rustls), when configured: services read `RFCL_TLS_CERT` and `RFCL_TLS_KEY` (PEM),
//!   clients `RFCL_TLS_CA` (the PEM certificate that signed the services'); a client with a CA
//!   speaks TLS to every address it dials.
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use thiserror::Error;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::transport::{
    Certificate, Channel, ClientTlsConfig, Endpoint, Identity, Server, ServerTlsConfig,
};
use tonic::{Request, Status};

/// Environment variable holding the run's token.
pub const TOKEN_ENV: &str = "RFCL_TOKEN";
/// Environment variable naming a file that holds the run's token.
pub const TOKEN_FILE_ENV: &str = "RFCL_TOKEN_FILE";
/// Environment variables of a service's TLS certificate chain and private key (PEM files).
pub const TLS_CERT_ENV: &str = "RFCL_TLS_CERT";
pub const TLS_KEY_ENV: &str = "RFCL_TLS_KEY";
/// Environment variable of the CA certificate clients trust (PEM file).
pub const TLS_CA_ENV: &str = "RFCL_TLS_CA";
/// Shortest token accepted: a guessable token is no authentication.
pub const MIN_TOKEN_CHARS: usize = 16;

const HEADER: &str = "authorization";
const SCHEME: &str = "Bearer ";

#[derive(Debug, Error)]
pub enum AuthError {
    #[error(
        "no run token: set {TOKEN_ENV} to the run's token or {TOKEN_FILE_ENV} to a file holding it \
         (every rfcl gRPC call is authenticated; `rfcl train` makes one per run)"
    )]
    Missing,
    #[error("both {TOKEN_ENV} and {TOKEN_FILE_ENV} are set: keep one")]
    Both,
    #[error("reading the run token from {path} ({TOKEN_FILE_ENV}): {error}")]
    Read {
        path: PathBuf,
        error: std::io::Error,
    },
    #[error(
        "the run token {origin} is not usable: {problem} (expected at least {MIN_TOKEN_CHARS} \
         visible ASCII characters, no spaces)"
    )]
    Invalid { origin: String, problem: String },
    #[error(
        "TLS: {var} is set but {missing} is not: a service needs both its certificate and its key"
    )]
    HalfTls {
        var: &'static str,
        missing: &'static str,
    },
    #[error("TLS: reading {path} ({var}): {error}")]
    TlsRead {
        var: &'static str,
        path: PathBuf,
        error: std::io::Error,
    },
}

/// The run's secret. Its `Debug` never shows it.
#[derive(Clone, PartialEq, Eq)]
pub struct Token(Arc<str>);

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(<redacted>)")
    }
}

impl Token {
    /// Checks a token: at least [`MIN_TOKEN_CHARS`] visible ASCII characters (it travels in an
    /// HTTP/2 header). Surrounding whitespace (a file's trailing newline) is trimmed.
    pub fn parse(raw: &str, origin: &str) -> Result<Token, AuthError> {
        let token = raw.trim();
        let invalid = |problem: String| AuthError::Invalid {
            origin: origin.to_string(),
            problem,
        };
        if let Some(c) = token.chars().find(|c| !c.is_ascii_graphic()) {
            return Err(invalid(format!("it contains {c:?}")));
        }
        if token.len() < MIN_TOKEN_CHARS {
            return Err(invalid(format!("it has {} characters", token.len())));
        }
        Ok(Token(token.into()))
    }

    /// A fresh random token: 256 bits from the operating system's generator, as hex.
    pub fn random() -> Token {
        let bytes: [u8; 32] = rand::random();
        let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        Token(hex.into())
    }

    /// The token from `RFCL_TOKEN` or from the file `RFCL_TOKEN_FILE` names.
    pub fn from_env() -> Result<Token, AuthError> {
        Self::from_vars(
            std::env::var(TOKEN_ENV).ok(),
            std::env::var_os(TOKEN_FILE_ENV).map(PathBuf::from),
        )
    }

    fn from_vars(value: Option<String>, file: Option<PathBuf>) -> Result<Token, AuthError> {
        match (value, file) {
            (Some(_), Some(_)) => Err(AuthError::Both),
            (Some(v), None) => Token::parse(&v, &format!("in {TOKEN_ENV}")),
            (None, Some(path)) => Token::read_file(&path),
            (None, None) => Err(AuthError::Missing),
        }
    }

    /// Reads a token file (a trailing newline is fine).
    pub fn read_file(path: &Path) -> Result<Token, AuthError> {
        let raw = std::fs::read_to_string(path).map_err(|error| AuthError::Read {
            path: path.to_path_buf(),
            error,
        })?;
        Token::parse(&raw, &format!("in {}", path.display()))
    }

    /// The token itself, e.g. to hand it to a child process's environment.
    pub fn expose(&self) -> &str {
        &self.0
    }

    fn header_value(&self) -> MetadataValue<Ascii> {
        format!("{SCHEME}{}", self.0)
            .parse()
            .expect("a checked token is a valid header value")
    }
}

/// Client side: stamps every call with the run's token.
#[derive(Clone)]
pub struct Stamp(MetadataValue<Ascii>);

impl Stamp {
    pub fn new(token: &Token) -> Self {
        Stamp(token.header_value())
    }
}

impl tonic::service::Interceptor for Stamp {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        request.metadata_mut().insert(HEADER, self.0.clone());
        Ok(request)
    }
}

/// A channel whose every call carries the run's token.
pub type AuthChannel = InterceptedService<Channel, Stamp>;

/// Wraps a connected channel so its calls carry `token`.
pub fn authenticated(channel: Channel, token: &Token) -> AuthChannel {
    InterceptedService::new(channel, Stamp::new(token))
}

/// Service side: lets a call through only with the run's token; counts the refused ones.
#[derive(Clone)]
pub struct Guard {
    expected: Arc<[u8]>,
    refused: Arc<AtomicU64>,
}

impl std::fmt::Debug for Guard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Guard")
            .field("refused", &self.refused())
            .finish_non_exhaustive()
    }
}

impl Guard {
    pub fn new(token: &Token) -> Self {
        Guard {
            expected: token.header_value().as_bytes().into(),
            refused: Arc::default(),
        }
    }

    /// Calls refused so far (no token, or a wrong one).
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }

    fn admits(&self, presented: Option<&[u8]>) -> bool {
        presented.is_some_and(|p| constant_time_eq(p, &self.expected))
    }
}

impl tonic::service::Interceptor for Guard {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        if self.admits(request.metadata().get(HEADER).map(|v| v.as_bytes())) {
            return Ok(request);
        }
        self.refused.fetch_add(1, Ordering::Relaxed);
        Err(Status::unauthenticated(
            "missing or wrong run token: set RFCL_TOKEN or RFCL_TOKEN_FILE to this run's token",
        ))
    }
}

/// Equal-length byte strings compared without an early exit, so the time taken does not tell how
/// much of a guessed token was right.
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// What a client needs to call rfcl services: the run's token and, when configured, the CA of
/// the services' TLS certificates.
#[derive(Clone, Debug)]
pub struct ClientAuth {
    pub token: Token,
    tls: Option<ClientTlsConfig>,
}

impl ClientAuth {
    /// The token and TLS settings of this process's environment.
    pub fn from_env() -> Result<Self, AuthError> {
        Ok(ClientAuth {
            token: Token::from_env()?,
            tls: client_tls_from_env()?,
        })
    }

    /// A token and no TLS.
    pub fn plain(token: Token) -> Self {
        ClientAuth { token, tls: None }
    }

    /// Speaks TLS, trusting the CA certificate in the PEM file `ca`.
    pub fn with_tls_ca(self, ca: &Path) -> Result<Self, AuthError> {
        Ok(ClientAuth {
            tls: Some(client_tls(ca)?),
            ..self
        })
    }

    /// Applies TLS to an endpoint when it is configured.
    pub fn endpoint(&self, endpoint: Endpoint) -> Result<Endpoint, tonic::transport::Error> {
        match &self.tls {
            Some(tls) => endpoint.tls_config(tls.clone()),
            None => Ok(endpoint),
        }
    }

    /// Wraps a connected channel so every call on it carries the token.
    pub fn wrap(&self, channel: Channel) -> AuthChannel {
        authenticated(channel, &self.token)
    }
}

/// What a service needs to check its callers: the run's token and, when configured, its TLS
/// identity.
#[derive(Clone)]
pub struct ServerAuth {
    pub guard: Guard,
    tls: Option<ServerTlsConfig>,
}

impl ServerAuth {
    /// The token and TLS settings of this process's environment.
    pub fn from_env() -> Result<Self, AuthError> {
        Ok(ServerAuth {
            guard: Guard::new(&Token::from_env()?),
            tls: server_tls_from_env()?,
        })
    }

    /// A token and no TLS.
    pub fn plain(token: &Token) -> Self {
        ServerAuth {
            guard: Guard::new(token),
            tls: None,
        }
    }

    /// Whether the service speaks TLS.
    pub fn tls(&self) -> bool {
        self.tls.is_some()
    }

    /// A server builder with TLS applied when it is configured.
    pub fn server(&self) -> Result<Server, tonic::transport::Error> {
        let builder = Server::builder();
        match &self.tls {
            Some(tls) => builder.tls_config(tls.clone()),
            None => Ok(builder),
        }
    }
}

/// A service's TLS identity from `RFCL_TLS_CERT` and `RFCL_TLS_KEY`; `None` when neither is set.
pub fn server_tls_from_env() -> Result<Option<ServerTlsConfig>, AuthError> {
    let cert = std::env::var_os(TLS_CERT_ENV).map(PathBuf::from);
    let key = std::env::var_os(TLS_KEY_ENV).map(PathBuf::from);
    match (cert, key) {
        (None, None) => Ok(None),
        (Some(_), None) => Err(AuthError::HalfTls {
            var: TLS_CERT_ENV,
            missing: TLS_KEY_ENV,
        }),
        (None, Some(_)) => Err(AuthError::HalfTls {
            var: TLS_KEY_ENV,
            missing: TLS_CERT_ENV,
        }),
        (Some(cert), Some(key)) => {
            let identity =
                Identity::from_pem(read_pem(TLS_CERT_ENV, &cert)?, read_pem(TLS_KEY_ENV, &key)?);
            Ok(Some(ServerTlsConfig::new().identity(identity)))
        }
    }
}

/// The CA clients trust from `RFCL_TLS_CA`; `None` when it is not set (plain HTTP/2).
pub fn client_tls_from_env() -> Result<Option<ClientTlsConfig>, AuthError> {
    std::env::var_os(TLS_CA_ENV)
        .map(|ca| client_tls(Path::new(&ca)))
        .transpose()
}

fn client_tls(ca: &Path) -> Result<ClientTlsConfig, AuthError> {
    let pem = read_pem(TLS_CA_ENV, ca)?;
    Ok(ClientTlsConfig::new().ca_certificate(Certificate::from_pem(pem)))
}

fn read_pem(var: &'static str, path: &Path) -> Result<Vec<u8>, AuthError> {
    std::fs::read(path).map_err(|error| AuthError::TlsRead {
        var,
        path: path.to_path_buf(),
        error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::service::Interceptor;

    fn token() -> Token {
        Token::parse("0123456789abcdef0123", "in a test").unwrap()
    }

    #[test]
    fn a_token_file_may_end_with_a_newline() {
        let dir = std::env::temp_dir().join(format!("rfcl-token-{}", std::process::id()));
        std::fs::write(&dir, "0123456789abcdef0123\n").unwrap();
        let read = Token::read_file(&dir).unwrap();
        std::fs::remove_file(&dir).unwrap();
        assert_eq!(read, token());
    }

    #[test]
    fn short_or_spaced_tokens_are_refused_with_their_origin() {
        let err = Token::parse("short", "in RFCL_TOKEN")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("in RFCL_TOKEN") && err.contains("5 characters"),
            "{err}"
        );
        let err = Token::parse("0123456789 abcdef0123", "in f")
            .unwrap_err()
            .to_string();
        assert!(err.contains("' '"), "{err}");
    }

    #[test]
    fn the_environment_gives_exactly_one_source() {
        assert!(matches!(
            Token::from_vars(None, None),
            Err(AuthError::Missing)
        ));
        assert!(matches!(
            Token::from_vars(Some("x".repeat(20)), Some("/f".into())),
            Err(AuthError::Both)
        ));
        assert_eq!(
            Token::from_vars(Some("0123456789abcdef0123".into()), None).unwrap(),
            token()
        );
        let err = Token::from_vars(None, Some("/nonexistent/rfcl-token".into())).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/rfcl-token"), "{err}");
    }

    #[test]
    fn random_tokens_are_valid_and_differ() {
        let (a, b) = (Token::random(), Token::random());
        assert_ne!(a, b);
        assert_eq!(a.expose().len(), 64);
        assert_eq!(Token::parse(a.expose(), "a test").unwrap(), a);
    }

    #[test]
    fn debug_never_shows_the_token() {
        assert_eq!(format!("{:?}", token()), "Token(<redacted>)");
    }

    #[test]
    fn the_guard_admits_the_stamped_token_and_counts_refusals() {
        let mut guard = Guard::new(&token());
        let stamped = Stamp::new(&token()).call(Request::new(())).unwrap();
        assert!(guard.call(stamped).is_ok());

        let other = Token::parse("fedcba9876543210fedc", "in a test").unwrap();
        let wrong = Stamp::new(&other).call(Request::new(())).unwrap();
        let status = guard.call(wrong).unwrap_err();
        assert_eq!(status.code(), tonic::Code::Unauthenticated);
        assert!(guard.call(Request::new(())).is_err());
        assert_eq!(guard.refused(), 2);
        // Clones share the count: the service and its metrics see one number.
        assert_eq!(guard.clone().refused(), 2);
    }

    #[test]
    fn constant_time_eq_compares_whole_strings() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"abcd"));
        assert!(!constant_time_eq(b"", b"a"));
    }
}
