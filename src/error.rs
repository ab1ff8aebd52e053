//! The library's error type.

use std::path::PathBuf;

/// Everything that can go wrong in the library, with enough context to act on it.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An I/O error on a named file.
    #[error("{path}: {source}")]
    Io {
        /// The file being read or written.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A file whose content does not follow its format.
    #[error("{path}: {message}")]
    Format {
        /// The offending file.
        path: PathBuf,
        /// What is wrong, with a line or byte position where known.
        message: String,
    },
    /// A checkpoint whose state dict does not fit the network: `key` is the first entry found
    /// missing, unexpected or mis-shaped.
    #[error("{path}: {key}: {message}")]
    StateDict {
        /// The checkpoint.
        path: PathBuf,
        /// The first offending state-dict key.
        key: String,
        /// What is wrong with it (expected and found shapes), and how many others are wrong.
        message: String,
    },
    /// A run (conversion, daemon) that ended by a failure; the message says which part failed.
    #[error("{0}")]
    Run(String),
    /// A command stopped by a signal before its input ended; what it wrote is complete up to
    /// there (exit status 130).
    #[error("{0}")]
    Interrupted(String),
    /// An argument or configuration value that cannot be used.
    #[error("invalid {what}: {message}")]
    Invalid {
        /// The name of the argument or setting.
        what: &'static str,
        /// Why it was rejected.
        message: String,
    },
}

impl Error {
    /// Builds an [`Error::Io`] for `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }

    /// Builds an [`Error::Format`] for `path`.
    pub fn format(path: impl Into<PathBuf>, message: impl Into<String>) -> Self {
        Error::Format {
            path: path.into(),
            message: message.into(),
        }
    }

    /// Builds an [`Error::Invalid`].
    pub fn invalid(what: &'static str, message: impl Into<String>) -> Self {
        Error::Invalid {
            what,
            message: message.into(),
        }
    }
}

/// The library's result type.
pub type Result<T> = std::result::Result<T, Error>;
