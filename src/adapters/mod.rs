//! Adapters to the outside world: forecast providers the daemon pulls
//! from, and MQTT (sensors in, valve commands and Home Assistant discovery
//! out).

pub mod forecast;
pub mod mqtt;
