mod latency_bench;
