-- Release the keys still held with this token (never another holder's), and wake a waiter of each
-- released key that someone waits for (acquire.lua marked it <key>:wanted): a token on <key>:wake, the
-- list the waiter blocks on (BLPOP), at most one token a list, for 1 s (one unclaimed costs a later
-- waiter one retry). Blocked clients are served in the order they blocked.
-- KEYS: the lock/claim keys. ARGV[1]: token. Returns how many were released.
local released = 0
for _, key in ipairs(KEYS) do
  if redis.call('GET', key) == ARGV[1] then
    redis.call('DEL', key)
    released = released + 1
    if redis.call('EXISTS', key .. ':wanted') == 1 then
      local wake = key .. ':wake'
      redis.call('RPUSH', wake, 1)
      redis.call('LTRIM', wake, -1, -1)
      redis.call('PEXPIRE', wake, 1000)
    end
  end
end
return released
