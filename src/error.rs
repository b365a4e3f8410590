//! One error type for the library. Every variant that comes from input names the file (and
//! the line where there is one), so that a user can fix the input without reading code.

use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A text file whose content is wrong at a known line (1-based).
    #[error("{}:{line}: {msg}", path.display())]
    Parse {
        path: PathBuf,
        line: usize,
        msg: String,
    },
    /// A file that is wrong as a whole (missing, unreadable, wrong image size or type, ...).
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    /// Invalid arguments or combinations that are not tied to one file.
    #[error("{0}")]
    Invalid(String),
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

impl Error {
    pub fn parse(path: &Path, line: usize, msg: impl Into<String>) -> Self {
        Error::Parse {
            path: path.to_path_buf(),
            line,
            msg: msg.into(),
        }
    }
    pub fn file(path: &Path, msg: impl std::fmt::Display) -> Self {
        Error::File {
            path: path.to_path_buf(),
            msg: msg.to_string(),
        }
    }
    pub fn invalid(msg: impl Into<String>) -> Self {
        Error::Invalid(msg.into())
    }
}

/// Reads a whole text file, mapping I/O errors to [`Error::File`].
pub fn read_text(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).map_err(|e| Error::file(path, format!("cannot read: {e}")))?;
    String::from_utf8(bytes).map_err(|e| {
        let line = 1 + e.as_bytes()[..e.utf8_error().valid_up_to()]
            .iter()
            .filter(|&&b| b == b'\n')
            .count();
        Error::parse(path, line, "not valid UTF-8 text")
    })
}
