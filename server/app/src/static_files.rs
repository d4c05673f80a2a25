//! Files over HTTP: the pages under `www-dir` (the router's fallback: `GET /` is `index.html`, `GET /console`
//! is `console.html`, `GET /<path>` the file at that path), and the one file responder they share with the
//! console's gallery: content type by extension, `Cache-Control: no-cache`, and single byte ranges, without which
//! Safari plays no video.

use std::io::SeekFrom;
use std::path::{Component, Path, PathBuf};

use axum::body::Body;
use axum::extract::State;
use axum::http::header::{
    ACCEPT_ENCODING, ACCEPT_RANGES, CACHE_CONTROL, CONTENT_ENCODING, CONTENT_LENGTH, CONTENT_RANGE, CONTENT_TYPE,
    RANGE, VARY,
};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, Uri};
use axum::response::{IntoResponse, Response};
use percent_encoding::percent_decode_str;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;

use crate::state::WwwState;

#[derive(Debug, thiserror::Error)]
pub enum FileError {
    #[error("`{0}` is not a path inside the served directory")]
    OutsideRoot(String),
    #[error("no file {}", .0.display())]
    NotFound(PathBuf),
    #[error("no file {}: the www-dir {} does not exist (set www-dir in the run configuration)", .path.display(), .root.display())]
    NoRoot { path: PathBuf, root: PathBuf },
    #[error("no route for {method} {path}")]
    NoRoute { method: Method, path: String },
    #[error("range `{range}` is outside the file's {len} bytes")]
    Range { range: String, len: u64 },
    #[error("{}: {source}", .path.display())]
    Io { path: PathBuf, source: std::io::Error },
}

impl IntoResponse for FileError {
    fn into_response(self) -> Response {
        let status = self.status();
        let mut response = (status, self.to_string()).into_response();
        if let Self::Range { len, .. } = self {
            let value = HeaderValue::from_str(&format!("bytes */{len}")).expect("ASCII");
            response.headers_mut().insert(CONTENT_RANGE, value);
        }
        response
    }
}

impl FileError {
    pub fn status(&self) -> StatusCode {
        match self {
            Self::OutsideRoot(_) => StatusCode::BAD_REQUEST,
            Self::NotFound(_) | Self::NoRoot { .. } | Self::NoRoute { .. } => StatusCode::NOT_FOUND,
            Self::Range { .. } => StatusCode::RANGE_NOT_SATISFIABLE,
            Self::Io { .. } => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }
}

/// The router's fallback: a page or asset under `www-dir`.
pub async fn serve(
    State(www): State<WwwState>,
    method: Method,
    uri: Uri,
    headers: HeaderMap,
) -> Result<Response, FileError> {
    if method != Method::GET && method != Method::HEAD {
        return Err(FileError::NoRoute { method, path: uri.path().to_owned() });
    }
    let relative = match uri.path() {
        "/" => "index.html".to_owned(),
        "/console" => "console.html".to_owned(),
        path => {
            let encoded = path.trim_start_matches('/');
            percent_decode_str(encoded)
                .decode_utf8()
                .map_err(|_| FileError::OutsideRoot(encoded.to_owned()))?
                .into_owned()
        }
    };
    let path = www.dir.join(relative_path(&relative)?);
    let served = match gzip_sibling(&path, &headers).await {
        Some(gz) => file_response_as(&gz, content_type(&path), &headers).await.map(|mut response| {
            response.headers_mut().insert(CONTENT_ENCODING, HeaderValue::from_static("gzip"));
            response
        }),
        None => file_response(&path, &headers).await,
    };
    let served = served.map(|mut response| {
        response.headers_mut().insert(VARY, HeaderValue::from_static("accept-encoding"));
        response
    });
    match served {
        Err(FileError::NotFound(path)) if !tokio::fs::metadata(&*www.dir).await.is_ok_and(|m| m.is_dir()) => {
            Err(FileError::NoRoot { path, root: www.dir.to_path_buf() })
        }
        other => other,
    }
}

/// `relative` as a path that stays inside the directory it is joined to: plain names only, so no `..`, root or
/// `.` can lead out of it.
pub fn relative_path(relative: &str) -> Result<&Path, FileError> {
    let path = Path::new(relative);
    let plain = path.components().all(|c| matches!(c, Component::Normal(_)));
    if relative.is_empty() || !plain {
        return Err(FileError::OutsideRoot(relative.to_owned()));
    }
    Ok(path)
}

/// `<path>.gz` when the client takes gzip, asks for the whole file, and the build left a compressed copy that is
/// not older than the file (client-wasm/build.sh compresses the 37 MB volunteer to 6 MB).
async fn gzip_sibling(path: &Path, request: &HeaderMap) -> Option<PathBuf> {
    let accepts_gzip = request
        .get(ACCEPT_ENCODING)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|coding| coding.split(';').next().is_some_and(|c| c.trim() == "gzip")));
    if !accepts_gzip || request.contains_key(RANGE) {
        return None;
    }
    let mut name = path.file_name()?.to_owned();
    name.push(".gz");
    let gz = path.with_file_name(name);
    let modified = |p: PathBuf| async move { tokio::fs::metadata(p).await.and_then(|m| m.modified()).ok() };
    let (original, compressed) = (modified(path.to_owned()).await?, modified(gz.clone()).await?);
    (compressed >= original).then_some(gz)
}

/// The file at `path` (or the byte range the request asks for), streamed.
pub async fn file_response(path: &Path, request: &HeaderMap) -> Result<Response, FileError> {
    file_response_as(path, content_type(path), request).await
}

/// [`file_response`] with the given content type (a compressed copy is served as what it decompresses to).
async fn file_response_as(path: &Path, content_type: &'static str, request: &HeaderMap) -> Result<Response, FileError> {
    let io = |source| FileError::Io { path: path.to_owned(), source };
    let len = match tokio::fs::metadata(path).await {
        Ok(meta) if meta.is_file() => meta.len(),
        Ok(_) => return Err(FileError::NotFound(path.to_owned())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(FileError::NotFound(path.to_owned())),
        Err(e) => return Err(io(e)),
    };
    let range = requested_range(request.get(RANGE), len)?;
    let mut file = tokio::fs::File::open(path).await.map_err(io)?;
    let (start, count) = match range {
        Some((start, end)) => (start, end - start + 1),
        None => (0, len),
    };
    if start > 0 {
        file.seek(SeekFrom::Start(start)).await.map_err(io)?;
    }
    let response = Response::builder()
        .status(if range.is_some() { StatusCode::PARTIAL_CONTENT } else { StatusCode::OK })
        .header(CONTENT_TYPE, content_type)
        .header(CONTENT_LENGTH, count)
        .header(CACHE_CONTROL, "no-cache")
        .header(ACCEPT_RANGES, "bytes");
    let response = match range {
        Some((start, end)) => response.header(CONTENT_RANGE, format!("bytes {start}-{end}/{len}")),
        None => response,
    };
    Ok(response.body(Body::from_stream(ReaderStream::new(file.take(count)))).expect("headers are valid"))
}

/// The one byte range (first and last byte) a `Range` header asks for. A missing, malformed or multi-range
/// header asks for the whole file (`None`), as HTTP allows; a range that starts past the end cannot be served.
fn requested_range(header: Option<&HeaderValue>, len: u64) -> Result<Option<(u64, u64)>, FileError> {
    let Some(spec) = header.and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("bytes=")) else {
        return Ok(None);
    };
    let Some((first, last)) = spec.split_once('-').filter(|_| !spec.contains(',')) else {
        return Ok(None);
    };
    let unsatisfiable = || FileError::Range { range: spec.to_owned(), len };
    let (start, end) = match (first.trim().parse::<u64>(), last.trim().parse::<u64>()) {
        (Ok(start), Ok(end)) if start <= end => (start, end.min(len.saturating_sub(1))),
        (Ok(start), Err(_)) if last.trim().is_empty() => (start, len.saturating_sub(1)),
        (Err(_), Ok(suffix)) if first.trim().is_empty() => {
            if suffix == 0 {
                return Err(unsatisfiable());
            }
            (len.saturating_sub(suffix), len.saturating_sub(1))
        }
        _ => return Ok(None),
    };
    if start >= len {
        return Err(unsatisfiable());
    }
    Ok(Some((start, end)))
}

/// The content type by extension; `application/wasm` is what lets browsers compile WebAssembly while it streams.
pub fn content_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()) {
        Some("html") => "text/html; charset=utf-8",
        Some("js" | "mjs") => "text/javascript; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("wasm") => "application/wasm",
        Some("json") => "application/json",
        Some("png") => "image/png",
        Some("svg") => "image/svg+xml",
        Some("webm") => "video/webm",
        Some("mp4") => "video/mp4",
        Some("txt" | "log" | "toml" | "jsonl") => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range(value: &str, len: u64) -> Result<Option<(u64, u64)>, FileError> {
        requested_range(Some(&HeaderValue::from_str(value).unwrap()), len)
    }

    #[test]
    fn byte_ranges() {
        assert_eq!(range("bytes=0-99", 1000).unwrap(), Some((0, 99)));
        assert_eq!(range("bytes=990-2000", 1000).unwrap(), Some((990, 999)));
        assert_eq!(range("bytes=500-", 1000).unwrap(), Some((500, 999)));
        assert_eq!(range("bytes=-100", 1000).unwrap(), Some((900, 999)));
        assert_eq!(range("bytes=-5000", 1000).unwrap(), Some((0, 999)));
        assert_eq!(range("bytes=0-1,5-6", 1000).unwrap(), None, "multi-range: the whole file");
        assert_eq!(range("bytes=x-y", 1000).unwrap(), None, "malformed: the whole file");
        assert_eq!(range("items=0-1", 1000).unwrap(), None);
        assert_eq!(requested_range(None, 1000).unwrap(), None);
        assert!(matches!(range("bytes=1000-", 1000), Err(FileError::Range { len: 1000, .. })));
        assert!(matches!(range("bytes=0-0", 0), Err(FileError::Range { .. })));
    }

    #[test]
    fn paths_stay_inside() {
        assert_eq!(relative_path("pkg/client_bg.wasm").unwrap(), Path::new("pkg/client_bg.wasm"));
        for bad in ["", "..", "../secret", "a/../../b", "/etc/passwd", "./x"] {
            let err = relative_path(bad).unwrap_err();
            assert_eq!(err.status(), StatusCode::BAD_REQUEST, "{bad}");
            assert!(err.to_string().contains(&format!("`{bad}`")), "{err}");
        }
    }
}
