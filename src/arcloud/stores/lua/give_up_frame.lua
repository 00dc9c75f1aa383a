-- Give up a queue entry of a map's frame, unless a commit recorded the frame: one step, so that the frame is
-- either processed or given up (commit.lua refuses a frame delivered from an entry given up), never both.
-- KEYS[1]: the map's processed-frames HASH, KEYS[2]: the entry's given-up mark (STRING: when, Unix s).
-- ARGV[1]: the frame key, ARGV[2]: now (Unix s), ARGV[3]: retention_s (how long either mark counts), ARGV[4]:
-- how long the given-up mark is kept (ms: its retention).
-- Returns 1 (given up: the mark set), 0 (the frame was processed: nothing written).
local recorded_at = redis.call('HGET', KEYS[1], ARGV[1])
if recorded_at and tonumber(recorded_at) >= tonumber(ARGV[2]) - tonumber(ARGV[3]) then
  return 0
end
redis.call('SET', KEYS[2], ARGV[2], 'PX', ARGV[4])
return 1
