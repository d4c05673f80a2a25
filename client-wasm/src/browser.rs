//! Small bridges to the browser: a monotonic clock, sleeping, yielding to the page between steps, and the size of
//! the module's memory.

use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;

/// The global scope (a window, or a worker's global scope).
fn global() -> js_sys::Object {
    js_sys::global()
}

/// Seconds since the page started, from `performance.now()`.
pub fn now_seconds() -> f64 {
    let performance = js_sys::Reflect::get(&global(), &"performance".into())
        .ok()
        .and_then(|p| p.dyn_into::<web_sys::Performance>().ok());
    performance.map_or(0.0, |p| p.now() / 1000.0)
}

/// Resolves after `ms` milliseconds (a `setTimeout`), letting the page render and handle events meanwhile.
pub async fn sleep_ms(ms: i32) {
    let promise = js_sys::Promise::new(&mut |resolve, _| {
        let set_timeout = js_sys::Reflect::get(&global(), &"setTimeout".into())
            .expect("setTimeout")
            .unchecked_into::<js_sys::Function>();
        set_timeout.call2(&JsValue::NULL, &resolve, &JsValue::from(ms)).expect("setTimeout call");
    });
    wasm_bindgen_futures::JsFuture::from(promise).await.ok();
}

/// Gives the page a turn (rendering, input, socket events) between long computations.
pub async fn yield_to_page() {
    sleep_ms(0).await;
}

/// Bytes of this module's linear memory: the most the volunteer has held at once (wasm memory grows and never
/// shrinks; wasm32 allows 4 GiB), the figure a base-size round must fit.
pub fn wasm_memory_bytes() -> f64 {
    let buffer = wasm_bindgen::memory().unchecked_into::<js_sys::WebAssembly::Memory>().buffer();
    buffer.unchecked_into::<js_sys::ArrayBuffer>().byte_length() as f64
}

/// A JS error value with `message`.
pub fn js_error(message: impl std::fmt::Display) -> JsValue {
    js_sys::Error::new(&message.to_string()).into()
}
