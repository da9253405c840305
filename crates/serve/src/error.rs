//! Errors: [`ServeError`] for starting and running the server (the library boundary),
//! [`ApiError`] for one request's answer (a 4xx naming the part and field, or a 5xx that
//! says what the server could not do).

use axum::http::{HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use std::path::PathBuf;

/// Why the server could not start or stopped abnormally.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// A setting is out of range or unsafe (`field` is the flag).
    #[error("{field}: {msg}")]
    Config {
        /// The flag or setting (`--bind`).
        field: String,
        /// What is wrong.
        msg: String,
    },
    /// A file or folder of the data directory could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// The listening socket could not be opened.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address asked for.
        addr: std::net::SocketAddr,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// The engine failed (loading the model).
    #[error(transparent)]
    Engine(#[from] recon_core::Error),
}

impl ServeError {
    /// A [`ServeError::Config`].
    pub fn config(field: impl Into<String>, msg: impl Into<String>) -> Self {
        ServeError::Config { field: field.into(), msg: msg.into() }
    }

    /// A [`ServeError::Io`].
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        ServeError::Io { path: path.into(), source }
    }
}

/// One request's error answer: the HTTP status and a JSON body
/// `{"error": {"status", "part", "field", "message"}}`. Input errors name the multipart
/// part (`rgb`, `options`, …) and the field inside it (`fx`, `image width/height`,
/// `samples`, …) with the message `recon infer` gives for the same input.
#[derive(Debug, Clone, PartialEq)]
pub struct ApiError {
    /// The HTTP status (4xx for the request, 5xx for the server).
    pub status: StatusCode,
    /// The multipart part (or path parameter) at fault, when there is one.
    pub part: Option<String>,
    /// The field inside that part, when known.
    pub field: Option<String>,
    /// What is wrong, in words.
    pub message: String,
    /// Seconds after which a retry may succeed (`Retry-After`), for 429 and 503.
    pub retry_after: Option<u64>,
}

impl ApiError {
    /// An error with `status` and a message, no part.
    pub fn new(status: StatusCode, message: impl Into<String>) -> Self {
        ApiError { status, part: None, field: None, message: message.into(), retry_after: None }
    }

    /// A 400 naming `part` and `field`.
    pub fn bad(part: &str, field: &str, message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, message).at(part, field)
    }

    /// The same error, naming `part` and `field`.
    pub fn at(mut self, part: &str, field: &str) -> Self {
        self.part = Some(part.to_string());
        self.field = Some(field.to_string());
        self
    }

    /// A 404 (no such job, file or route).
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, message)
    }

    /// A 503 for a server-side failure (disk, shutdown): never a 500.
    pub fn unavailable(message: impl Into<String>) -> Self {
        Self::new(StatusCode::SERVICE_UNAVAILABLE, message)
    }

    /// The JSON body.
    pub fn body(&self) -> serde_json::Value {
        serde_json::json!({"error": {
            "status": self.status.as_u16(),
            "part": self.part,
            "field": self.field,
            "message": self.message,
        }})
    }
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}", self.status.as_u16(), self.message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut r = (self.status, axum::Json(self.body())).into_response();
        if let Some(s) = self.retry_after {
            r.headers_mut().insert(axum::http::header::RETRY_AFTER, HeaderValue::from(s));
        }
        r
    }
}

/// The HTTP status of an engine error about an input: a claim over a bound is 413, any
/// other input error 400.
pub(crate) fn input_status(e: &recon_core::Error) -> StatusCode {
    match e {
        recon_core::Error::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
        _ => StatusCode::BAD_REQUEST,
    }
}
