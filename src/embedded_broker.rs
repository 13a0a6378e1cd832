//! A small MQTT 3.1.1 broker on 127.0.0.1 for `rtu2mqtt demo` on a machine without one, so that
//! `mosquitto_sub`, MQTT Explorer, Node-RED or Home Assistant can connect to the demo.
//!
//! It does what the demo needs and no more: retained messages, wildcard subscriptions, last
//! wills, keep-alive, client takeover. Subscriptions are granted at QoS 0 (MQTT lets a server
//! grant less than asked), so nothing is stored per client; publications in are acknowledged at
//! the QoS they came with. The packet codec is rumqttc's (already a dependency); a full broker
//! crate (rumqttd) would pull a web server and a metrics exporter into the daemon's build for a
//! demo convenience.

use std::collections::{BTreeMap, HashMap};
use std::net::{Ipv4Addr, SocketAddr};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::{Bytes, BytesMut};
use rumqttc::mqttbytes::v4::{
    ConnAck, ConnectReturnCode, Packet, PubAck, PubComp, PubRec, Publish, SubAck,
    SubscribeReasonCode, UnsubAck,
};
use rumqttc::mqttbytes::{matches, valid_filter, valid_topic, Error as CodecError, QoS};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, oneshot, watch};
use tracing::debug;

/// Largest packet accepted from a client.
const MAX_PACKET: usize = 1 << 20;
/// Packets queued for one subscriber; a client that falls this far behind is disconnected
/// rather than slowing everyone else down.
const CLIENT_QUEUE: usize = 8192;

/// A running embedded broker; dropping it stops the broker and closes every connection.
pub struct EmbeddedBroker {
    port: u16,
    stop: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl EmbeddedBroker {
    /// Listens on 127.0.0.1:`port` (0 picks a free port) on a thread of its own.
    pub fn start(port: u16) -> std::io::Result<Self> {
        let listener = std::net::TcpListener::bind(SocketAddr::from((Ipv4Addr::LOCALHOST, port)))?;
        listener.set_nonblocking(true)?;
        let port = listener.local_addr()?.port();
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let (stop_tx, stop_rx) = oneshot::channel();
        let thread = std::thread::Builder::new()
            .name("mqtt-broker".into())
            .spawn(move || {
                runtime.block_on(async move {
                    match TcpListener::from_std(listener) {
                        Ok(listener) => serve(listener, stop_rx).await,
                        Err(err) => debug!(%err, "embedded broker cannot listen"),
                    }
                });
            })?;
        Ok(Self {
            port,
            stop: Some(stop_tx),
            thread: Some(thread),
        })
    }

    pub fn port(&self) -> u16 {
        self.port
    }
}

impl Drop for EmbeddedBroker {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

struct Subscriber {
    client_id: String,
    filters: Vec<String>,
    outgoing: mpsc::Sender<Publish>,
    kick: watch::Sender<bool>,
}

#[derive(Default)]
struct Hub {
    next_connection: u64,
    subscribers: HashMap<u64, Subscriber>,
    retained: BTreeMap<String, Bytes>,
}

impl Hub {
    /// Stores (or, with an empty payload, clears) a retained message and forwards to every
    /// matching subscription, once per client.
    fn route(&mut self, topic: &str, payload: Bytes, retain: bool) {
        if retain {
            if payload.is_empty() {
                self.retained.remove(topic);
            } else {
                self.retained.insert(topic.to_owned(), payload.clone());
            }
        }
        for subscriber in self.subscribers.values() {
            if subscriber.filters.iter().any(|f| matches(topic, f)) {
                let publish = Publish::new(topic, QoS::AtMostOnce, payload.clone());
                if subscriber.outgoing.try_send(publish).is_err() {
                    let _ = subscriber.kick.send(true);
                }
            }
        }
    }

    fn retained_matching(&self, filter: &str) -> Vec<Publish> {
        self.retained
            .iter()
            .filter(|(topic, _)| matches(topic, filter))
            .map(|(topic, payload)| {
                let mut publish = Publish::new(topic.as_str(), QoS::AtMostOnce, payload.clone());
                publish.retain = true;
                publish
            })
            .collect()
    }
}

async fn serve(listener: TcpListener, mut stop: oneshot::Receiver<()>) {
    let hub = Arc::new(Mutex::new(Hub::default()));
    let mut connections = tokio::task::JoinSet::new();
    loop {
        tokio::select! {
            _ = &mut stop => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    let _ = stream.set_nodelay(true);
                    connections.spawn(serve_client(stream, Arc::clone(&hub), peer));
                }
                Err(err) => debug!(%err, "embedded broker: accept failed"),
            },
            Some(_) = connections.join_next(), if !connections.is_empty() => {}
        }
    }
    connections.shutdown().await;
}

/// Why a connection ended: a clean DISCONNECT suppresses the last will.
enum Ending {
    Clean,
    Dropped,
}

async fn serve_client(mut stream: TcpStream, hub: Arc<Mutex<Hub>>, peer: SocketAddr) {
    let mut input = BytesMut::with_capacity(4096);
    let connect = match read_packet(&mut stream, &mut input).await {
        Some(Packet::Connect(connect)) => connect,
        _ => return,
    };
    let (outgoing_tx, mut outgoing) = mpsc::channel(CLIENT_QUEUE);
    let (kick_tx, mut kick) = watch::channel(false);
    let id = {
        let mut hub = lock(&hub);
        // A second connection with the same client id takes the session over.
        for subscriber in hub.subscribers.values() {
            if subscriber.client_id == connect.client_id && !connect.client_id.is_empty() {
                let _ = subscriber.kick.send(true);
            }
        }
        hub.next_connection += 1;
        let id = hub.next_connection;
        hub.subscribers.insert(
            id,
            Subscriber {
                client_id: connect.client_id.clone(),
                filters: Vec::new(),
                outgoing: outgoing_tx,
                kick: kick_tx,
            },
        );
        id
    };
    debug!(%peer, client = %connect.client_id, "embedded broker: client connected");
    let keep_alive = match connect.keep_alive {
        0 => None,
        seconds => Some(Duration::from_millis(u64::from(seconds) * 1500)),
    };
    let mut output = BytesMut::new();
    let ending = if write_packet(
        &mut stream,
        &mut output,
        Packet::ConnAck(ConnAck::new(ConnectReturnCode::Success, false)),
    )
    .await
    {
        converse(
            &mut stream,
            &mut input,
            &mut output,
            &hub,
            id,
            &mut outgoing,
            &mut kick,
            keep_alive,
        )
        .await
    } else {
        Ending::Dropped
    };
    let mut hub = lock(&hub);
    hub.subscribers.remove(&id);
    if let (Ending::Dropped, Some(will)) = (ending, connect.last_will) {
        if valid_topic(&will.topic) {
            hub.route(&will.topic, will.message, will.retain);
        }
    }
    debug!(%peer, client = %connect.client_id, "embedded broker: client gone");
}

#[allow(clippy::too_many_arguments)]
async fn converse(
    stream: &mut TcpStream,
    input: &mut BytesMut,
    output: &mut BytesMut,
    hub: &Arc<Mutex<Hub>>,
    id: u64,
    outgoing: &mut mpsc::Receiver<Publish>,
    kick: &mut watch::Receiver<bool>,
    keep_alive: Option<Duration>,
) -> Ending {
    loop {
        // Complete packets already buffered first, then wait for more bytes, a delivery, a
        // takeover, or the keep-alive to run out.
        let packet = match Packet::read(input, MAX_PACKET) {
            Ok(packet) => packet,
            Err(CodecError::InsufficientBytes(_)) => {
                let idle = async {
                    match keep_alive {
                        Some(limit) => tokio::time::sleep(limit).await,
                        None => std::future::pending().await,
                    }
                };
                tokio::select! {
                    read = stream.read_buf(input) => match read {
                        Ok(0) | Err(_) => return Ending::Dropped,
                        Ok(_) => continue,
                    },
                    Some(publish) = outgoing.recv() => {
                        if !write_packet(stream, output, Packet::Publish(publish)).await {
                            return Ending::Dropped;
                        }
                        continue;
                    }
                    _ = kick.changed() => return Ending::Dropped,
                    () = idle => return Ending::Dropped,
                }
            }
            Err(_) => return Ending::Dropped,
        };
        let reply = match packet {
            Packet::Publish(publish) => {
                if !valid_topic(&publish.topic) {
                    return Ending::Dropped;
                }
                lock(hub).route(&publish.topic, publish.payload, publish.retain);
                match publish.qos {
                    QoS::AtMostOnce => None,
                    QoS::AtLeastOnce => Some(Packet::PubAck(PubAck::new(publish.pkid))),
                    QoS::ExactlyOnce => Some(Packet::PubRec(PubRec::new(publish.pkid))),
                }
            }
            Packet::PubRel(rel) => Some(Packet::PubComp(PubComp::new(rel.pkid))),
            Packet::Subscribe(subscribe) => {
                let mut codes = Vec::new();
                let mut retained = Vec::new();
                {
                    let mut hub = lock(hub);
                    for filter in &subscribe.filters {
                        if valid_filter(&filter.path) {
                            codes.push(SubscribeReasonCode::Success(QoS::AtMostOnce));
                            retained.extend(hub.retained_matching(&filter.path));
                            if let Some(me) = hub.subscribers.get_mut(&id) {
                                if !me.filters.contains(&filter.path) {
                                    me.filters.push(filter.path.clone());
                                }
                            }
                        } else {
                            codes.push(SubscribeReasonCode::Failure);
                        }
                    }
                }
                let ack = Packet::SubAck(SubAck::new(subscribe.pkid, codes));
                if !write_packet(stream, output, ack).await {
                    return Ending::Dropped;
                }
                for publish in retained {
                    if !write_packet(stream, output, Packet::Publish(publish)).await {
                        return Ending::Dropped;
                    }
                }
                None
            }
            Packet::Unsubscribe(unsubscribe) => {
                if let Some(me) = lock(hub).subscribers.get_mut(&id) {
                    me.filters.retain(|f| !unsubscribe.topics.contains(f));
                }
                Some(Packet::UnsubAck(UnsubAck::new(unsubscribe.pkid)))
            }
            Packet::PingReq => Some(Packet::PingResp),
            Packet::Disconnect => return Ending::Clean,
            Packet::Connect(_) => return Ending::Dropped,
            // Acknowledgements of our QoS 0 deliveries cannot come; anything else is ignored.
            _ => None,
        };
        if let Some(reply) = reply {
            if !write_packet(stream, output, reply).await {
                return Ending::Dropped;
            }
        }
    }
}

async fn read_packet(stream: &mut TcpStream, input: &mut BytesMut) -> Option<Packet> {
    let first = async {
        loop {
            match Packet::read(input, MAX_PACKET) {
                Ok(packet) => return Some(packet),
                Err(CodecError::InsufficientBytes(_)) => match stream.read_buf(input).await {
                    Ok(0) | Err(_) => return None,
                    Ok(_) => {}
                },
                Err(_) => return None,
            }
        }
    };
    // A client that connects and says nothing is dropped.
    tokio::time::timeout(Duration::from_secs(10), first)
        .await
        .ok()
        .flatten()
}

async fn write_packet(stream: &mut TcpStream, output: &mut BytesMut, packet: Packet) -> bool {
    output.clear();
    if packet.write(output, usize::MAX).is_err() {
        return false;
    }
    stream.write_all(output).await.is_ok()
}

fn lock(hub: &Mutex<Hub>) -> std::sync::MutexGuard<'_, Hub> {
    hub.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rumqttc::{AsyncClient, Event, MqttOptions};

    async fn client(port: u16, id: &str) -> (AsyncClient, rumqttc::EventLoop) {
        let mut options = MqttOptions::new(id, "127.0.0.1", port);
        options.set_keep_alive(Duration::from_secs(5));
        AsyncClient::new(options, 16)
    }

    async fn next_publish(eventloop: &mut rumqttc::EventLoop) -> rumqttc::Publish {
        loop {
            match eventloop.poll().await.expect("connection") {
                Event::Incoming(Packet::Publish(p)) => return p,
                _ => continue,
            }
        }
    }

    async fn until_suback(eventloop: &mut rumqttc::EventLoop) {
        loop {
            if let Event::Incoming(Packet::SubAck(ack)) =
                eventloop.poll().await.expect("connection")
            {
                assert!(ack
                    .return_codes
                    .iter()
                    .all(|c| *c == SubscribeReasonCode::Success(QoS::AtMostOnce)));
                return;
            }
        }
    }

    #[tokio::test]
    async fn retained_wildcards_live_messages_and_wills() {
        let broker = EmbeddedBroker::start(0).expect("start");
        let port = broker.port();
        let timeout = Duration::from_secs(10);

        // A publisher with a will leaves a retained value behind.
        let (publisher, mut publisher_loop) = {
            let mut options = MqttOptions::new("publisher", "127.0.0.1", port);
            options.set_last_will(rumqttc::LastWill::new(
                "/status",
                "offline",
                QoS::AtLeastOnce,
                true,
            ));
            AsyncClient::new(options, 16)
        };
        publisher
            .publish("/devices/a/controls/K1", QoS::AtLeastOnce, true, "1")
            .await
            .unwrap();
        publisher
            .publish("/devices/a/controls/K2", QoS::AtLeastOnce, true, "0")
            .await
            .unwrap();
        let mut acks = 0;
        while acks < 2 {
            if let Event::Incoming(Packet::PubAck(_)) = publisher_loop.poll().await.unwrap() {
                acks += 1;
            }
        }

        // A late subscriber gets the retained values with the retain flag set.
        let (subscriber, mut subscriber_loop) = client(port, "subscriber").await;
        subscriber
            .subscribe("/devices/+/controls/#", QoS::AtLeastOnce)
            .await
            .unwrap();
        subscriber
            .subscribe("/status", QoS::AtLeastOnce)
            .await
            .unwrap();
        let mut retained = BTreeMap::new();
        tokio::time::timeout(timeout, async {
            while retained.len() < 2 {
                let p = next_publish(&mut subscriber_loop).await;
                assert!(p.retain, "{p:?}");
                retained.insert(p.topic.clone(), p.payload.clone());
            }
        })
        .await
        .expect("retained values");
        assert_eq!(retained["/devices/a/controls/K1"], Bytes::from("1"));
        assert_eq!(retained["/devices/a/controls/K2"], Bytes::from("0"));

        // A live message arrives without the retain flag; a non-matching one does not arrive.
        publisher
            .publish("/other", QoS::AtMostOnce, false, "x")
            .await
            .unwrap();
        publisher
            .publish("/devices/a/controls/K1", QoS::AtMostOnce, true, "0")
            .await
            .unwrap();
        let live = tokio::time::timeout(timeout, async {
            loop {
                tokio::select! {
                    p = next_publish(&mut subscriber_loop) => return p,
                    _ = publisher_loop.poll() => {}
                }
            }
        })
        .await
        .expect("live message");
        assert_eq!(live.topic, "/devices/a/controls/K1");
        assert_eq!(live.payload, Bytes::from("0"));
        assert!(!live.retain);

        // The publisher vanishes without DISCONNECT: its will is delivered.
        drop(publisher);
        drop(publisher_loop);
        let will = tokio::time::timeout(timeout, next_publish(&mut subscriber_loop))
            .await
            .expect("will");
        assert_eq!(will.topic, "/status");
        assert_eq!(will.payload, Bytes::from("offline"));

        // Clearing a retained topic: a new subscriber no longer gets it.
        let (cleaner, mut cleaner_loop) = client(port, "cleaner").await;
        cleaner
            .publish("/devices/a/controls/K2", QoS::AtLeastOnce, true, "")
            .await
            .unwrap();
        cleaner
            .subscribe("/devices/#", QoS::AtMostOnce)
            .await
            .unwrap();
        until_suback(&mut cleaner_loop).await;
        let first = tokio::time::timeout(timeout, next_publish(&mut cleaner_loop))
            .await
            .expect("retained K1");
        assert_eq!(first.topic, "/devices/a/controls/K1");
        assert_eq!(
            broker_retained_topics(&broker_state_probe(port).await),
            vec!["/devices/a/controls/K1".to_owned(), "/status".to_owned()]
        );
    }

    /// All retained topics, read by a fresh client that subscribes to `#` and stops at a marker.
    async fn broker_state_probe(port: u16) -> Vec<rumqttc::Publish> {
        let (probe, mut probe_loop) = client(port, "probe").await;
        probe.subscribe("#", QoS::AtMostOnce).await.unwrap();
        until_suback(&mut probe_loop).await;
        probe
            .publish("/zz-marker", QoS::AtMostOnce, false, "m")
            .await
            .unwrap();
        let mut seen = Vec::new();
        tokio::time::timeout(Duration::from_secs(10), async {
            loop {
                let p = next_publish(&mut probe_loop).await;
                if p.topic == "/zz-marker" {
                    break;
                }
                seen.push(p);
            }
        })
        .await
        .expect("marker");
        seen
    }

    fn broker_retained_topics(seen: &[rumqttc::Publish]) -> Vec<String> {
        seen.iter()
            .filter(|p| p.retain)
            .map(|p| p.topic.clone())
            .collect()
    }
}
