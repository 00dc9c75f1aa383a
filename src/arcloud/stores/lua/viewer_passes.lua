-- One API key's list of live viewer passes, bounded (``redis_viewer_passes``): one step, so concurrent draws of a key
-- neither lose the list's expiry nor end more of its passes than the bound asks.
-- KEYS[1] the key's list (a ZSET: pass digest -> its expiry, Unix ms). ARGV[1] now (Unix ms), ARGV[2] the new pass's
-- digest, ARGV[3] its expiry (Unix ms), ARGV[4] the bound.
-- Drops the expired, pops those that would end first past the bound (returned: the caller deletes those passes), adds
-- the new one, and keeps the list until its last pass ends.
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', ARGV[1])
local held = redis.call('ZCARD', KEYS[1])
local ended = {}
local bound = tonumber(ARGV[4])
if held >= bound then
  local popped = redis.call('ZPOPMIN', KEYS[1], held - bound + 1)
  for i = 1, #popped, 2 do ended[#ended + 1] = popped[i] end
end
redis.call('ZADD', KEYS[1], ARGV[3], ARGV[2])
local last = redis.call('ZRANGE', KEYS[1], -1, -1, 'WITHSCORES')
redis.call('PEXPIREAT', KEYS[1], last[2])
return ended
