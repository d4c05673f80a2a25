//! JSON control messages (text WebSocket frames). Updates travel as binary frames, see [`crate::codec`].

use serde::{Deserialize, Serialize};

/// Bumped on any incompatible change to the control messages or the binary update format.
pub const PROTOCOL_VERSION: u16 = 1;

/// What a client runs on, so the server can plan tasks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Capabilities {
    /// e.g. "ndarray", "wgpu", "webgpu".
    pub backend: String,
    pub memory_bytes: u64,
}

/// What a client reports after a round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundMetrics {
    pub round: u64,
    pub examples: u64,
    pub train_loss: f64,
    /// Seconds spent on the round: model fetch, training and upload.
    pub seconds: f64,
    /// Bytes this client has sent since it joined (control and update frames).
    pub bytes_up: u64,
    /// Bytes this client has received since it joined (control messages and model downloads).
    pub bytes_down: u64,
}

/// Client -> server.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ClientMessage {
    /// First message on every connection.
    Join {
        protocol_version: u16,
        auth_token: Option<String>,
        /// Stable name chosen by the volunteer; sampling and aggregation order follow it.
        name: String,
        capabilities: Capabilities,
    },
    /// Keep-alive for idle connections (e.g. behind proxies); the server only notes it.
    Heartbeat,
    /// Announces the binary update frames that follow.
    UpdateHeader {
        round: u64,
        examples: u64,
        train_loss: f64,
        payload_bytes: u64,
    },
    Metrics(RoundMetrics),
    /// Loss on the client's own held-out split, when the task asked for it.
    EvalResult {
        round: u64,
        examples: u64,
        loss: f64,
    },
}

/// Parameters the strategy hands to clients (e.g. FedProx's proximal term).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StrategyParams {
    pub name: String,
    /// Weight of the proximal term `mu/2 * ||w - w_global||^2`; 0 for FedAvg.
    pub proximal_mu: f64,
}

/// One round of local work for one client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoundTask {
    pub round: u64,
    /// Version of the global trainable tensors to start from (`GET /model/{version}`).
    pub model_version: u64,
    pub local_steps: u32,
    pub batch_size: u32,
    pub lr: f64,
    /// Seed for this client's local shuffling in this round.
    pub seed: u64,
    pub strategy: StrategyParams,
    /// Milliseconds from the task until the server closes the round.
    pub deadline_ms: u64,
    /// Whether the client should also report [`ClientMessage::EvalResult`].
    pub eval_request: bool,
}

/// Why the server refused something.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    ProtocolVersion,
    Unauthorized,
    MalformedMessage,
    MalformedFrame,
    ChecksumMismatch,
    Oversized,
    MissingTensor,
    UnexpectedTensor,
    ShapeMismatch,
    NonFinite,
    UnexpectedMessage,
    StaleRound,
    ShuttingDown,
}

impl ErrorCode {
    /// Errors after which the server closes the connection.
    pub fn is_fatal(self) -> bool {
        matches!(
            self,
            Self::ProtocolVersion | Self::Unauthorized | Self::ShuttingDown
        )
    }

    pub fn as_str(self) -> &'static str {
        match self {
            Self::ProtocolVersion => "protocol_version",
            Self::Unauthorized => "unauthorized",
            Self::MalformedMessage => "malformed_message",
            Self::MalformedFrame => "malformed_frame",
            Self::ChecksumMismatch => "checksum_mismatch",
            Self::Oversized => "oversized",
            Self::MissingTensor => "missing_tensor",
            Self::UnexpectedTensor => "unexpected_tensor",
            Self::ShapeMismatch => "shape_mismatch",
            Self::NonFinite => "non_finite",
            Self::UnexpectedMessage => "unexpected_message",
            Self::StaleRound => "stale_round",
            Self::ShuttingDown => "shutting_down",
        }
    }
}

/// Server -> client.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ServerMessage {
    Welcome {
        client_id: u64,
        protocol_version: u16,
        /// Largest binary frame the server accepts; updates are chunked to fit.
        max_frame_bytes: u32,
    },
    RoundTask(RoundTask),
    Error {
        code: ErrorCode,
        message: String,
    },
    /// The round ended; `accepted` is false when it had too few updates and will be retried.
    RoundClosed {
        round: u64,
        accepted: bool,
        model_version: u64,
        updates: u32,
    },
    /// The run is over; the client may disconnect.
    Finished {
        rounds: u64,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_are_tagged_snake_case() {
        let join = ClientMessage::Join {
            protocol_version: PROTOCOL_VERSION,
            auth_token: None,
            name: "c0".into(),
            capabilities: Capabilities {
                backend: "ndarray".into(),
                memory_bytes: 1 << 30,
            },
        };
        let json = serde_json::to_string(&join).unwrap();
        assert!(
            json.starts_with(r#"{"type":"join","protocol_version":1"#),
            "{json}"
        );
        assert_eq!(serde_json::from_str::<ClientMessage>(&json).unwrap(), join);

        let err = ServerMessage::Error {
            code: ErrorCode::NonFinite,
            message: "x".into(),
        };
        let json = serde_json::to_string(&err).unwrap();
        assert_eq!(
            json,
            r#"{"type":"error","code":"non_finite","message":"x"}"#
        );
        assert_eq!(serde_json::from_str::<ServerMessage>(&json).unwrap(), err);
    }

    #[test]
    fn code_strings_match_serde() {
        for code in [
            ErrorCode::ProtocolVersion,
            ErrorCode::StaleRound,
            ErrorCode::MalformedFrame,
        ] {
            assert_eq!(
                serde_json::to_string(&code).unwrap(),
                format!("\"{}\"", code.as_str())
            );
        }
    }
}
