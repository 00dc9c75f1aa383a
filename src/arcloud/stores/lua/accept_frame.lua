-- Record a frame key as accepted by the ingest.
-- KEYS[1] the map's accepted SET, KEYS[2] its failed SET; ARGV[1] the frame key.
-- Returns 1 when the frame is new or failed before (queue it), 0 for a duplicate.
local added = redis.call('SADD', KEYS[1], ARGV[1])
local refailed = redis.call('SREM', KEYS[2], ARGV[1])
if added == 1 or refailed == 1 then return 1 end
return 0
