//! What the page shows: every change of the volunteer's state goes to the page's callback as one JSON object
//! (`{"kind": ..., ...}`), which www/join.js draws.

use serde_json::{Value, json};
use wasm_bindgen::JsValue;

/// The page's status callback.
#[derive(Clone)]
pub struct StatusSink {
    callback: js_sys::Function,
}

impl StatusSink {
    pub fn new(callback: js_sys::Function) -> Self {
        Self { callback }
    }

    /// Sends `{"kind": kind, ...fields}` to the page.
    pub fn send(&self, kind: &str, mut fields: Value) {
        fields["kind"] = json!(kind);
        // A failing page callback must not stop training; the page's own error handler reports it.
        let _ = self.callback.call1(&JsValue::NULL, &JsValue::from_str(&fields.to_string()));
    }
}
