//! The gRPC codec of the generated services: prost's, except that a received message is
//! decoded from one contiguous byte slice rather than from tonic's buffer type. prost reads
//! packed floats one at a time, and from a slice that is 2.4 times faster (a fragment of 30
//! agents × 200 steps: 1.4 ms instead of 3.5 ms on the development machine).

use std::marker::PhantomData;

use prost::Message;
use prost::bytes::Buf;
use tonic::Status;
use tonic::codec::{Codec, DecodeBuf, Decoder};
use tonic_prost::ProstEncoder;

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
    U: Message + Default + Send + 'static,
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

impl<U: Message + Default> Decoder for ContiguousDecoder<U> {
    type Item = U;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<U>, Status> {
        // One message's bytes; tonic hands them over without copying.
        let bytes = buf.copy_to_bytes(buf.remaining());
        U::decode(bytes.as_ref())
            .map(Some)
            // As tonic-prost reports it: INTERNAL with prost's "failed to decode …".
            .map_err(|e| Status::internal(e.to_string()))
    }
}
