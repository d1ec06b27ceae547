//! The gRPC codec of the generated services: prost's, except that a received message is
//! decoded from one contiguous byte slice rather than from tonic's buffer type. prost reads
//! packed floats one at a time, and from a slice that is 2.4 times faster (a fragment of 30
//! agents × 200 steps: 1.4 ms instead of 3.5 ms on the development machine).
//!
//! Bytes that do not decode are the sender's fault: a request is answered with
//! `INVALID_ARGUMENT` naming the RPC and prost's error (tonic-prost says `INTERNAL`, which
//! reads as the learner's bug). A reply that does not decode stays `INTERNAL` on the actor's
//! side, which it retries.

use std::marker::PhantomData;

use prost::Message;
use prost::bytes::Buf;
use tonic::Status;
use tonic::codec::{Codec, DecodeBuf, Decoder};
use tonic_prost::ProstEncoder;

use crate::proto;

/// The RPC a message travels in, and whether it is that RPC's request or its reply.
pub trait RpcMessage {
    const RPC: &'static str;
    const REQUEST: bool;
}

macro_rules! rpc_messages {
    ($($message:ident => $rpc:literal, $request:literal;)*) => {
        $(impl RpcMessage for proto::$message {
            const RPC: &'static str = $rpc;
            const REQUEST: bool = $request;
        })*
    };
}

rpc_messages! {
    RegisterRequest => "Register", true;
    RegisterReply => "Register", false;
    RolloutFragment => "PushRollouts", true;
    PushSummary => "PushRollouts", false;
    WatchPolicyRequest => "WatchPolicy", true;
    PolicyWeights => "WatchPolicy", false;
    StatusRequest => "Status", true;
    StatusReply => "Status", false;
}

/// What every decode error's message contains, so a handler can tell one from other stream
/// errors.
pub const DECODE_ERROR: &str = "could not be decoded";

/// Whether `status` is this codec's answer to a request that did not decode.
pub fn is_request_decode_error(status: &Status) -> bool {
    status.code() == tonic::Code::InvalidArgument && status.message().contains(DECODE_ERROR)
}

#[derive(Debug, Clone)]
pub struct ContiguousCodec<T, U>(PhantomData<(T, U)>);

impl<T, U> Default for ContiguousCodec<T, U> {
    fn default() -> Self {
        ContiguousCodec(PhantomData)
    }
}

impl<T, U> Codec for ContiguousCodec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + RpcMessage + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = ProstEncoder<T>;
    type Decoder = ContiguousDecoder<U>;

    fn encoder(&mut self) -> Self::Encoder {
        ProstEncoder::default()
    }

    fn decoder(&mut self) -> Self::Decoder {
        ContiguousDecoder(PhantomData)
    }
}

#[derive(Debug, Clone)]
pub struct ContiguousDecoder<U>(PhantomData<U>);

impl<U: Message + Default + RpcMessage> Decoder for ContiguousDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        // One message's bytes; tonic hands them over without copying.
        let bytes = buf.copy_to_bytes(buf.remaining());
        U::decode(bytes.as_ref())
            .map(Some)
            .map_err(decode_error::<U>)
    }
}

fn decode_error<U: RpcMessage>(error: prost::DecodeError) -> Status {
    if U::REQUEST {
        Status::invalid_argument(format!(
            "{}: the request message {DECODE_ERROR}: {error}",
            U::RPC
        ))
    } else {
        Status::internal(format!("{}: the reply {DECODE_ERROR}: {error}", U::RPC))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Field 1 with wire type 7, which protobuf does not have.
    const GARBAGE: &[u8] = &[0x0f, 0x01];

    #[test]
    fn an_undecodable_request_is_the_senders_fault_and_names_its_rpc() {
        let error = proto::RolloutFragment::decode(GARBAGE).unwrap_err();
        let status = decode_error::<proto::RolloutFragment>(error);
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(
            status
                .message()
                .starts_with("PushRollouts: the request message could not be decoded: "),
            "{status:?}"
        );
        assert!(is_request_decode_error(&status));
    }

    #[test]
    fn an_undecodable_reply_stays_internal_so_actors_retry() {
        let error = proto::RegisterReply::decode(GARBAGE).unwrap_err();
        let status = decode_error::<proto::RegisterReply>(error);
        assert_eq!(status.code(), tonic::Code::Internal);
        assert!(
            status.message().starts_with("Register: the reply"),
            "{status:?}"
        );
        assert!(!is_request_decode_error(&status));
    }
}
