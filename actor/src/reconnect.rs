//! Staying connected to a learner that may restart: back-off with jitter between attempts,
//! which failures deserve a retry, and the outbox stream that hands the same fragments to
//! whichever connection is current.

use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::sync::mpsc;
use tonic::Code;

use junction_common::proto;

use crate::ledger::FragmentLog;

/// Exponential back-off with "equal jitter": attempt `n` waits a uniform draw from
/// `[d/2, d]` with `d = min(max, initial · 2ⁿ)`, so many actors that lost the same learner
/// do not all come back in the same instant, and no wait exceeds `max`.
pub struct Backoff {
    initial: Duration,
    max: Duration,
    next: Duration,
    /// SplitMix64 state; jitter needs spread, not quality.
    state: u64,
}

impl Backoff {
    pub fn new(initial: Duration, max: Duration, seed: u64) -> Self {
        let initial = initial.max(Duration::from_millis(1));
        let max = max.max(initial);
        Backoff {
            initial,
            max,
            next: initial,
            state: seed,
        }
    }

    /// The wait before the next attempt; each call doubles the ceiling up to `max`.
    pub fn next_delay(&mut self) -> Duration {
        let ceiling = self.next;
        self.next = (self.next * 2).min(self.max);
        let fraction = (self.random() >> 11) as f64 / (1u64 << 53) as f64;
        ceiling.mul_f64(0.5 + 0.5 * fraction)
    }

    /// After a connection succeeded: the next outage starts from `initial` again.
    pub fn reset(&mut self) {
        self.next = self.initial;
    }

    fn random(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
}

/// Would trying again help? A dead or restarting learner (unavailable, reset streams, a full
/// set of stream slots) is worth waiting for; a refused token, another protocol version or
/// fragments the learner calls invalid will fail the same way every time.
pub fn retryable(status: &tonic::Status) -> bool {
    !matches!(
        status.code(),
        Code::Unauthenticated
            | Code::PermissionDenied
            | Code::InvalidArgument
            | Code::FailedPrecondition
            | Code::Unimplemented
    )
}

/// The outbox as one connection's rollout stream. Fragments stay in the outbox (shared by
/// every connection, bounded) until a stream takes them, so a fragment produced while the
/// learner is away goes out on the next connection. Once `ended` is set, the stream of a
/// connection that broke yields nothing more, leaving the outbox to the next one.
pub struct OutboxStream {
    outbox: Arc<Mutex<mpsc::Receiver<proto::RolloutFragment>>>,
    ended: Arc<AtomicBool>,
    /// Fragments this stream handed to the transport.
    taken: Arc<AtomicU64>,
    /// The connection's actor id, its ledger and number, once known ([`OutboxStream::on_connection`]).
    connection: Option<Connection>,
}

struct Connection {
    actor_id: String,
    log: Arc<FragmentLog>,
    number: u64,
}

impl OutboxStream {
    pub fn new(
        outbox: Arc<Mutex<mpsc::Receiver<proto::RolloutFragment>>>,
        ended: Arc<AtomicBool>,
        taken: Arc<AtomicU64>,
    ) -> Self {
        OutboxStream {
            outbox,
            ended,
            taken,
            connection: None,
        }
    }

    /// Hands fragments over as `actor_id`, the id this connection registered, and records
    /// each in `log` as sent on connection `number`. A fragment produced while the learner
    /// was away carries the id of an earlier registration, which a restarted learner never
    /// issued (or issued to another actor): re-stamped, it names its sender.
    pub fn on_connection(mut self, actor_id: String, log: Arc<FragmentLog>, number: u64) -> Self {
        self.connection = Some(Connection {
            actor_id,
            log,
            number,
        });
        self
    }
}

impl tokio_stream::Stream for OutboxStream {
    type Item = proto::RolloutFragment;

    fn poll_next(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if self.ended.load(Ordering::Acquire) {
            return Poll::Ready(None);
        }
        let Ok(mut outbox) = self.outbox.lock() else {
            return Poll::Ready(None);
        };
        let mut polled = outbox.poll_recv(cx);
        if let Poll::Ready(Some(fragment)) = &mut polled {
            self.taken.fetch_add(1, Ordering::Relaxed);
            if let Some(connection) = &self.connection {
                fragment.actor_id.clone_from(&connection.actor_id);
                connection.log.sent(fragment.sequence, connection.number);
            }
        }
        polled
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio_stream::StreamExt;

    #[test]
    fn backoff_doubles_with_jitter_up_to_its_bound_and_resets() {
        let (initial, max) = (Duration::from_millis(100), Duration::from_secs(2));
        let mut backoff = Backoff::new(initial, max, 7);
        let delays: Vec<Duration> = (0..10).map(|_| backoff.next_delay()).collect();
        let ceilings = [100u64, 200, 400, 800, 1600, 2000, 2000, 2000, 2000, 2000];
        for (delay, ceiling) in delays.iter().zip(ceilings) {
            let ceiling = Duration::from_millis(ceiling);
            assert!(
                *delay >= ceiling / 2 && *delay <= ceiling,
                "{delay:?} outside [{:?}, {ceiling:?}]",
                ceiling / 2
            );
        }
        // Jitter: the waits at the bound are not all the same.
        assert!(delays[5..].windows(2).any(|w| w[0] != w[1]), "{delays:?}");
        // Other seeds spread differently (actors do not retry in lockstep).
        let mut other = Backoff::new(initial, max, 8);
        let others: Vec<Duration> = (0..10).map(|_| other.next_delay()).collect();
        assert_ne!(delays, others);
        backoff.reset();
        assert!(backoff.next_delay() <= initial);
    }

    #[test]
    fn only_failures_that_can_pass_are_retried() {
        for code in [
            Code::Unavailable,
            Code::Unknown,
            Code::Internal,
            Code::Cancelled,
            Code::DeadlineExceeded,
            Code::ResourceExhausted,
        ] {
            assert!(retryable(&tonic::Status::new(code, "")), "{code:?}");
        }
        for code in [
            Code::Unauthenticated,
            Code::InvalidArgument,
            Code::FailedPrecondition,
        ] {
            assert!(!retryable(&tonic::Status::new(code, "")), "{code:?}");
        }
    }

    #[tokio::test]
    async fn an_ended_stream_leaves_the_outbox_to_the_next_one() {
        let (tx, rx) = mpsc::channel(4);
        let outbox = Arc::new(Mutex::new(rx));
        let fragment = |sequence| proto::RolloutFragment {
            sequence,
            ..Default::default()
        };
        for sequence in 0..3 {
            tx.send(fragment(sequence)).await.unwrap();
        }
        let (first_ended, taken) = (
            Arc::new(AtomicBool::new(false)),
            Arc::new(AtomicU64::new(0)),
        );
        let mut first = OutboxStream::new(
            Arc::clone(&outbox),
            Arc::clone(&first_ended),
            Arc::clone(&taken),
        );
        assert_eq!(first.next().await.map(|f| f.sequence), Some(0));
        first_ended.store(true, Ordering::Release);
        assert!(
            first.next().await.is_none(),
            "a broken connection's stream stops"
        );
        let mut second =
            OutboxStream::new(outbox, Arc::new(AtomicBool::new(false)), Arc::clone(&taken));
        assert_eq!(second.next().await.map(|f| f.sequence), Some(1));
        assert_eq!(second.next().await.map(|f| f.sequence), Some(2));
        drop(tx);
        assert!(
            second.next().await.is_none(),
            "the rollout side closed the outbox"
        );
        assert_eq!(taken.load(Ordering::Relaxed), 3);
    }
}
