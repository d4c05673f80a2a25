//! Downloads with progress, each presenting the volunteer's session, cached in the browser's Cache API by a
//! version key, so the frozen weights and the shard cross the network once per version however often the page
//! reloads.

use js_sys::{Reflect, Uint8Array};
use wasm_bindgen::JsCast;
use wasm_bindgen::prelude::*;
use wasm_bindgen_futures::JsFuture;
use web_sys::{Cache, CacheStorage, Response};

use crate::browser::js_error;

/// The Cache API store every download is kept in.
const CACHE_NAME: &str = "fedvla-downloads";

/// Where a download came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    Cache,
    Network,
}

/// The page's cache, when the browser offers one (it needs a secure context: https or localhost).
async fn open_cache() -> Option<Cache> {
    let caches = Reflect::get(&js_sys::global(), &"caches".into()).ok()?.dyn_into::<CacheStorage>().ok()?;
    JsFuture::from(caches.open(CACHE_NAME)).await.ok()?.dyn_into::<Cache>().ok()
}

async fn response_bytes(response: &Response) -> Result<Vec<u8>, JsValue> {
    let buffer = JsFuture::from(response.array_buffer()?).await?;
    Ok(Uint8Array::new(&buffer).to_vec())
}

/// `GET url` with `Authorization: Bearer <session>`, reading the body chunk by chunk and reporting
/// `(received, total)` bytes (total 0 when unknown).
pub async fn fetch_with_progress(
    url: &str,
    session: &str,
    mut on_progress: impl FnMut(u64, u64),
) -> Result<Vec<u8>, JsValue> {
    let fetch = Reflect::get(&js_sys::global(), &"fetch".into())?.unchecked_into::<js_sys::Function>();
    let (init, headers) = (js_sys::Object::new(), js_sys::Object::new());
    Reflect::set(&headers, &"authorization".into(), &format!("Bearer {session}").into())?;
    Reflect::set(&init, &"headers".into(), &headers)?;
    let response: Response =
        JsFuture::from(fetch.call2(&JsValue::NULL, &url.into(), &init)?.unchecked_into::<js_sys::Promise>())
            .await?
            .dyn_into()?;
    if !response.ok() {
        let text = JsFuture::from(response.text()?).await?.as_string().unwrap_or_default();
        return Err(js_error(format!("GET {url}: {} {}", response.status(), text)));
    }
    let total = response.headers().get("content-length")?.and_then(|v| v.parse().ok()).unwrap_or(0u64);
    let Some(body) = response.body() else { return response_bytes(&response).await };
    let reader = body.get_reader().unchecked_into::<web_sys::ReadableStreamDefaultReader>();
    let mut bytes = Vec::with_capacity(total as usize);
    loop {
        let chunk = JsFuture::from(reader.read()).await?;
        if Reflect::get(&chunk, &"done".into())?.is_truthy() {
            break;
        }
        bytes.extend(Uint8Array::new(&Reflect::get(&chunk, &"value".into())?).to_vec());
        on_progress(bytes.len() as u64, total);
    }
    Ok(bytes)
}

/// The bytes at `url`, from the cache under `key` when a previous visit stored them, else downloaded (with
/// progress, presenting `session`) and stored. `key` must change whenever the content does (it carries a content
/// hash).
pub async fn cached(
    url: &str,
    key: &str,
    session: &str,
    on_progress: impl FnMut(u64, u64),
) -> Result<(Vec<u8>, Source), JsValue> {
    let cache = open_cache().await;
    if let Some(cache) = &cache {
        let hit = JsFuture::from(cache.match_with_str(key)).await?;
        if let Ok(response) = hit.dyn_into::<Response>() {
            return Ok((response_bytes(&response).await?, Source::Cache));
        }
    }
    let bytes = fetch_with_progress(url, session, on_progress).await?;
    if let Some(cache) = &cache {
        // Copied straight into a JS array, not first into a second buffer of the module's memory (which never
        // shrinks: at the base size the frozen weights are 0.7 GB of wasm32's 4 GiB).
        let copy = Uint8Array::from(bytes.as_slice());
        let response = Response::new_with_opt_buffer_source(Some(&copy))?;
        // A full cache (quota) only costs the next visit a download.
        let _ = JsFuture::from(cache.put_with_str(key, &response)).await;
    }
    Ok((bytes, Source::Network))
}
