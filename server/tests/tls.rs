//! TLS on loopback: a server with a certificate made here speaks only HTTPS and WSS. Volunteers that trust the
//! certificate join `wss://` and run a whole federation (setup, weights and updates all over TLS); one that trusts
//! only the Mozilla roots, or speaks plain `ws://` to it, gets nowhere, and the server goes on serving.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use fedvla_aggregator::config::ComputeDevice;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_federation::{Introduction, NamedTensors, routes};
use fedvla_server::native_client::{
    Dialer, NativeTransport, Volunteer, VolunteerData, admitted, http_request, simulated_identity, volunteer,
};
use hyper::body::Bytes;

/// A self-signed certificate for 127.0.0.1 and its key, as PEM files in `dir`.
fn certificate(dir: &Path) -> (PathBuf, PathBuf) {
    let rcgen::CertifiedKey { cert, signing_key } =
        rcgen::generate_simple_self_signed(vec!["127.0.0.1".to_owned(), "localhost".to_owned()]).unwrap();
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, signing_key.serialize_pem()).unwrap();
    (cert_path, key_path)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn volunteers_join_over_tls_and_nothing_else_gets_in() {
    let tmp = tempfile::tempdir().unwrap();
    let (cert, key) = certificate(tmp.path());
    let cfg = config(&format!("tls-cert={} tls-key={}", cert.display(), key.display()));
    let run_dir = RunDir::create(&tmp.path().join("run"), &cfg).unwrap();
    let handle = start(cfg, run_dir).await;
    let addr = handle.addr();

    // The Mozilla roots do not vouch for a self-signed certificate.
    let untrusted = NativeTransport::connect(&format!("wss://{addr}")).await.err().expect("an untrusted server");
    assert!(format!("{untrusted}").contains("certificate"), "{untrusted}");
    // Plain HTTP and WebSocket to a TLS listener get no answer.
    assert!(NativeTransport::connect(&format!("ws://{addr}")).await.is_err());
    let model = routes::model(0);
    let plain = Dialer::plain(&addr.to_string());
    assert!(http_request(&plain, hyper::Request::get(&model), Bytes::new()).await.is_err());
    // Trusting it, a volunteer is admitted over WSS and downloads over HTTPS with its session (one announcing an own
    // dataset: it holds no shard the others ask for) ...
    let intro = Introduction { name: "observer".into(), auth_token: None, shard: None, own_dataset: true };
    let url = format!("wss://{addr}");
    let (observer, _) = admitted(&url, Some(&cert), &simulated_identity("observer"), &intro).await.unwrap();
    let weights = observer.get(&model).await.unwrap();
    assert!(NamedTensors::from_safetensors(&weights).is_ok());

    // ... and three volunteers run the federation over WSS, the server unmoved by the connections it refused.
    let clients: Vec<_> = (0..3)
        .map(|shard| {
            let (url, cert) = (format!("wss://{addr}"), cert.clone());
            tokio::spawn(async move {
                let name = format!("client-{shard}");
                let data = VolunteerData::Shard(Some(shard));
                let identity = simulated_identity(&name);
                let v = Volunteer {
                    server: &url,
                    ca_cert: Some(&cert),
                    name: &name,
                    identity: &identity,
                    data,
                    auth_token: None,
                    attack: None,
                    device: ComputeDevice::Cpu,
                };
                volunteer(v, |_| {}).await.map_err(|e| e.to_string())
            })
        })
        .collect();
    assert_eq!(handle.finish().await.unwrap().completed_rounds, 2);
    for client in clients {
        assert_eq!(client.await.unwrap().unwrap().rounds_trained, 2);
    }
}

#[test]
fn a_server_with_half_a_tls_configuration_or_unreadable_files_does_not_start() {
    let refused = fedvla_aggregator::config::RunConfig::default().with_overrides("tls-cert=cert.pem").unwrap_err();
    assert!(refused.to_string().contains("tls-key"), "{refused}");
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("missing.pem");
    let err = fedvla_app::tls::acceptor(&missing, &missing).err().expect("no such file");
    assert!(err.to_string().contains("missing.pem"), "{err}");
    let (cert, _) = certificate(tmp.path());
    let err = fedvla_app::tls::acceptor(&cert, &cert).err().expect("a certificate is no key");
    assert!(err.to_string().contains("private key"), "{err}");
}
