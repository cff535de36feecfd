//! Prometheus metrics of the daemon.

use prometheus::{
    CounterVec, Encoder, GaugeVec, Histogram, HistogramOpts, IntCounter, IntCounterVec, IntGauge,
    Opts, Registry, TextEncoder,
};

/// The daemon's metrics and their registry.
pub struct Metrics {
    registry: Registry,
    pub measurements: IntCounter,
    pub cycles: IntCounterVec,
    pub degraded: IntCounterVec,
    pub solve_seconds: Histogram,
    pub theta: GaugeVec,
    pub setpoint: GaugeVec,
    pub webhooks: IntCounterVec,
    pub water_mm: CounterVec,
    pub water_m3: CounterVec,
    pub mqtt_received: IntCounter,
    pub mqtt_refused: IntCounterVec,
    pub mqtt_duplicates: IntCounter,
    pub mqtt_published: IntCounterVec,
    pub mqtt_connected: IntGauge,
    pub mqtt_connections: IntCounter,
    pub mqtt_ingest_seconds: Histogram,
    pub cycles_refused: IntCounter,
    pub cycle_lateness_seconds: Histogram,
    pub leases_held: IntGauge,
    pub lease_age_seconds: prometheus::Gauge,
    pub database_up: IntGauge,
    pub replica: GaugeVec,
    pub estimates_deferred: IntCounterVec,
    pub estimates_pending: IntGauge,
}

impl Metrics {
    pub fn new() -> Metrics {
        let registry = Registry::new();
        let measurements = IntCounter::new(
            "rootzone_measurements_ingested_total",
            "Measurements stored (API and simulated fields)",
        )
        .expect("valid metric");
        let cycles = IntCounterVec::new(
            Opts::new(
                "rootzone_control_cycles_total",
                "Control cycles by solver status",
            ),
            &["status"],
        )
        .expect("valid metric");
        let degraded = IntCounterVec::new(
            Opts::new(
                "rootzone_degraded_cycles_total",
                "Control cycles that ran in a degraded mode, by flag",
            ),
            &["flag"],
        )
        .expect("valid metric");
        let solve_seconds = Histogram::with_opts(
            HistogramOpts::new("rootzone_solve_seconds", "Zone-MPC solve time").buckets(vec![
                0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0,
            ]),
        )
        .expect("valid metric");
        let theta = GaugeVec::new(
            Opts::new(
                "rootzone_field_theta",
                "Latest water content of a field [m3/m3]",
            ),
            &["field"],
        )
        .expect("valid metric");
        let setpoint = GaugeVec::new(
            Opts::new(
                "rootzone_field_setpoint_mm",
                "Current irrigation setpoint of a field [mm per period]",
            ),
            &["field"],
        )
        .expect("valid metric");
        let webhooks = IntCounterVec::new(
            Opts::new(
                "rootzone_webhook_deliveries_total",
                "Webhook deliveries by outcome (delivered, failed)",
            ),
            &["outcome"],
        )
        .expect("valid metric");
        // water a field was told to apply, booked when the next setpoint
        // replaces (or the period ends for) the one that applied it
        let water_mm = CounterVec::new(
            Opts::new(
                "rootzone_field_irrigation_mm_total",
                "Irrigation applied by finished setpoints of a field [mm]",
            ),
            &["field"],
        )
        .expect("valid metric");
        let water_m3 = CounterVec::new(
            Opts::new(
                "rootzone_field_irrigation_m3_total",
                "Irrigation applied by finished setpoints of a field with an area [m3]",
            ),
            &["field"],
        )
        .expect("valid metric");
        let mqtt_received = IntCounter::new(
            "rootzone_mqtt_messages_received_total",
            "MQTT messages received on the daemon's subscriptions",
        )
        .expect("valid metric");
        let mqtt_refused = IntCounterVec::new(
            Opts::new(
                "rootzone_mqtt_readings_refused_total",
                "MQTT sensor messages refused (never stored), by reason",
            ),
            &["reason"],
        )
        .expect("valid metric");
        let mqtt_duplicates = IntCounter::new(
            "rootzone_mqtt_readings_duplicate_total",
            "MQTT readings already stored with the same value (redeliveries)",
        )
        .expect("valid metric");
        let mqtt_published = IntCounterVec::new(
            Opts::new(
                "rootzone_mqtt_publications_total",
                "MQTT publications of states and commands, by outcome (queued, dropped)",
            ),
            &["outcome"],
        )
        .expect("valid metric");
        let mqtt_connected = IntGauge::new(
            "rootzone_mqtt_connected",
            "1 while connected to the MQTT broker with the sensor subscription granted",
        )
        .expect("valid metric");
        let mqtt_connections = IntCounter::new(
            "rootzone_mqtt_connections_total",
            "MQTT connections made (ConnAck received)",
        )
        .expect("valid metric");
        let mqtt_ingest_seconds = Histogram::with_opts(
            HistogramOpts::new(
                "rootzone_mqtt_ingest_seconds",
                "Time from an MQTT reading's arrival to its commit",
            )
            .buckets(vec![
                0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0,
            ]),
        )
        .expect("valid metric");
        let cycles_refused = IntCounter::new(
            "rootzone_cycles_refused_total",
            "Scheduled cycles not stored: their boundary had run (elsewhere) or the lease ended",
        )
        .expect("valid metric");
        let cycle_lateness_seconds = Histogram::with_opts(
            HistogramOpts::new(
                "rootzone_cycle_lateness_seconds",
                "Wall time from a period boundary to its stored cycle",
            )
            .buckets(vec![
                0.01, 0.05, 0.1, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0,
            ]),
        )
        .expect("valid metric");
        let leases_held = IntGauge::new(
            "rootzone_leases_held",
            "Fields whose lease this replica holds (every field on SQLite)",
        )
        .expect("valid metric");
        let lease_age_seconds = prometheus::Gauge::new(
            "rootzone_lease_renewal_age_seconds",
            "Wall time since this replica last renewed its leases (the lease lag)",
        )
        .expect("valid metric");
        let database_up = IntGauge::new(
            "rootzone_database_up",
            "1 while the database answers, 0 while it is lost (cycles paused)",
        )
        .expect("valid metric");
        let replica = GaugeVec::new(
            Opts::new("rootzone_replica_info", "This replica: its id and storage"),
            &["replica", "storage"],
        )
        .expect("valid metric");
        let estimates_deferred = IntCounterVec::new(
            Opts::new(
                "rootzone_deferred_estimates_total",
                "State estimates brought up to date after their cycle, by outcome \
                 (updated; superseded: a later cycle or the lease came first; failed)",
            ),
            &["outcome"],
        )
        .expect("valid metric");
        let estimates_pending = IntGauge::new(
            "rootzone_deferred_estimates_pending",
            "Fields whose state estimate waits to be brought up to date after their cycle",
        )
        .expect("valid metric");
        for c in [
            Box::new(cycles_refused.clone()) as Box<dyn prometheus::core::Collector>,
            Box::new(estimates_deferred.clone()),
            Box::new(estimates_pending.clone()),
            Box::new(cycle_lateness_seconds.clone()),
            Box::new(leases_held.clone()),
            Box::new(lease_age_seconds.clone()),
            Box::new(database_up.clone()),
            Box::new(replica.clone()),
            Box::new(mqtt_received.clone()),
            Box::new(mqtt_refused.clone()),
            Box::new(mqtt_duplicates.clone()),
            Box::new(mqtt_published.clone()),
            Box::new(mqtt_connected.clone()),
            Box::new(mqtt_connections.clone()),
            Box::new(mqtt_ingest_seconds.clone()),
            Box::new(water_mm.clone()),
            Box::new(water_m3.clone()),
            Box::new(webhooks.clone()),
            Box::new(measurements.clone()),
            Box::new(cycles.clone()),
            Box::new(degraded.clone()),
            Box::new(solve_seconds.clone()),
            Box::new(theta.clone()),
            Box::new(setpoint.clone()),
        ] {
            registry.register(c).expect("unique metric names");
        }
        Metrics {
            registry,
            measurements,
            cycles,
            degraded,
            solve_seconds,
            theta,
            setpoint,
            webhooks,
            water_mm,
            water_m3,
            mqtt_received,
            mqtt_refused,
            mqtt_duplicates,
            mqtt_published,
            mqtt_connected,
            mqtt_connections,
            mqtt_ingest_seconds,
            cycles_refused,
            cycle_lateness_seconds,
            leases_held,
            lease_age_seconds,
            database_up,
            replica,
            estimates_deferred,
            estimates_pending,
        }
    }

    /// The text exposition format.
    pub fn render(&self) -> String {
        let mut buffer = Vec::new();
        let _ = TextEncoder::new().encode(&self.registry.gather(), &mut buffer);
        String::from_utf8(buffer).unwrap_or_default()
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}
