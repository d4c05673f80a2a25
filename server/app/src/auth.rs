//! The credential an HTTP request presents: `Authorization: Bearer <token>`, read in one place for the
//! volunteers' routes (run token, upload sessions) and the operator console.

use axum::http::HeaderMap;
use axum::http::header::AUTHORIZATION;

/// The `Bearer` credential of a request, if it has one.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers.get(AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "))
}
