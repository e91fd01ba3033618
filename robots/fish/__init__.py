"""The soft fish: a CO2 canister, two valves and a tapered tail of two bidirectional channels;
escape manoeuvres, forward swimming and heading control."""
